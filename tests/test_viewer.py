"""The viewer, server side: the scene's nodes, streaming, re-runs that cancel
older ones, carve by view, the roi read-out, --result, and that the server
stops and frees its port.  (The browser test is tests/test_viewer_browser.py.)"""

import socket
import time

import numpy as np
import pytest
from test_carving import ring, sphere_mask

from organlab.carving import ProgressiveCarver, carve
from organlab.grid import VoxelGrid

pytest.importorskip("viser")


def _port_free(port):
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _nodes(server):
    return set(server.scene._handle_from_node_name)


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    from organlab.synthetic import with_true_cameras

    return with_true_cameras("sample_sessions/aaa_phantom", tmp_path_factory.mktemp("viewer") / "aaa")


@pytest.fixture(scope="module")
def app(sample):
    """Every third view of the sample, 2 mm voxels (quick)."""
    from organlab.viewer import SessionViewer

    said = []

    def say(line):  # each start-up line, and whether the page answered when it was said
        import urllib.request

        up = None
        if " at http" in line:
            with urllib.request.urlopen(line.split(" at ")[1].split()[0], timeout=10) as r:
                up = r.status
        said.append((line, up))

    v = SessionViewer(sample, voxel_size=2.0, views=range(0, 36, 3), port=0, say=say)
    v.said = said
    assert v.wait(timeout=180), v.errors
    yield v
    v.stop()


def test_startup_says_the_url_first_then_its_steps(app):
    # a cold numba cache (no `make warm`) adds one "compiling" line: test_compiling_is_said checks it
    lines = [line for line, _ in app.said if not line.startswith("  compiling:")]
    # the address comes first, with the page already served, before the views, cameras and silhouettes are read
    assert lines[0] == f"organlab view: {app.session.name} at {app.url}  (Ctrl-C stops)" and app.said[0][1] == 200
    assert lines[1:] == ["  starting: reading 12 views", "  starting: cameras (given in session.json)",
                         "  starting: background and silhouette model"], lines
    assert app.status.startswith("start-up: done in")


def test_compiling_is_said(app):
    """A numba kernel compiling while the viewer runs (its cache missed) is said once and shown in the page."""
    from numba import njit

    def organlab_test_kernel(x):
        return x + 1

    n0, status = app.compiling.count, app.status
    try:
        assert njit(organlab_test_kernel)(1) == 2  # a new function: compiled, never in the cache
        assert app.compiling.count == n0 + 1 and app.compiling.seconds > 0
        assert app.controls.status.content == "*start-up: compiling numba kernels (the first run after installing; once)*"
        assert njit(organlab_test_kernel)(1) == 2 and app.compiling.count == n0 + 2  # a new dispatcher: again
        said = [line for line, _ in app.said if line.startswith("  compiling:")]
        # said once, however many kernels compile (the first one named)
        assert len(said) == 1 and "make warm" in said[0] and (n0 > 0 or "organlab_test_kernel" in said[0]), said
    finally:
        app.status = status
        app.controls.show_status(status)


# ------------------------------------------------------------------ LiveView
def test_live_view_streams_the_progressive_hull_and_frees_its_port():
    """A scene the session defaults never saw: a sphere seen by 6 cameras."""
    from organlab.surface import mesh_from_volume
    from organlab.viewer import LiveView
    from organlab.viewer._scene import surface_voxels

    grid = VoxelGrid.from_roi((-20, -20, -20), (20, 20, 20), 2.0)
    cams = ring(6, 250.0, 80.0, f=400.0)
    masks = [sphere_mask(c, (1.0, -2.0, 0.5), 15.0) for c in cams]
    live = LiveView(grid=grid, port=0)
    port = live.port
    assert not _port_free(port) and live.url == f"http://127.0.0.1:{port}"
    ref = ProgressiveCarver(grid)
    counts = []
    for c, m in zip(cams, masks):
        image = np.repeat((m * 200 + 30).astype(np.uint8)[..., None], 3, axis=2)
        live.add_view(image, c, m)
        occ = ref.add_view(m, c)
        pts = live._handles["voxels"].points
        # after each view: the surface voxels of the hull so far, float32, inside the grid
        assert pts.dtype == np.float32 and len(pts) == surface_voxels(occ).sum()
        lo, hi = grid.bounds
        assert (pts >= lo).all() and (pts <= hi).all()
        counts.append(len(pts))
    assert counts[0] > counts[-1]  # the hull is refined as views arrive
    with pytest.raises(ValueError, match="image_size"):
        live.add_view(np.zeros((10, 10, 3), np.uint8), cams[0])
    with pytest.raises(TypeError, match="Camera"):
        live.add_view(image, "camera")
    with pytest.raises(ValueError, match="grid"):
        live.set_voxels(np.ones((3, 3, 3), bool), grid)
    np.testing.assert_array_equal(occ, carve(masks, cams, grid))
    live.set_mesh(mesh_from_volume(occ, grid))
    nodes = _nodes(live.server)
    assert {"/turntable", "/turntable/axis", "/turntable/plate", "/voxels", "/mesh"} <= nodes
    assert {f"/views/{i:03d}" for i in range(6)} <= nodes
    np.testing.assert_allclose(live._handles["mesh"].vertices.min(0), mesh_from_volume(occ, grid).vertices.min(0), atol=1e-4)
    live.stop()
    for _ in range(50):  # the listening socket closes within a moment
        if _port_free(port):
            break
        time.sleep(0.1)
    assert _port_free(port)


# ------------------------------------------------------------------ session viewer
def test_session_scene_and_measurements(app, sample):
    from organlab.session import load_session

    res = app.result
    nodes = _nodes(app.live.server)
    assert {"/turntable", "/voxels", "/mesh"} <= nodes
    assert sum(n.startswith("/views/") for n in nodes) == 12
    ref = load_session(sample).reference["volume_mm3"]
    # 12 views at 2 mm: the hull holds the specimen and exceeds it by what 12
    # views cannot carve; measured +1.0 %, bound 5 %
    assert 1.0 < res.mesh.volume / ref < 1.05
    assert res.mesh.is_watertight
    # agreement: IoU of the hull's projection and the silhouette; measured 0.981-0.984
    # over the 12 views; a wrong camera or mask gives far less (next test)
    assert res.agreement.shape == (12,) and res.agreement.min() > 0.95
    assert "Volume" in app.controls.measure.content and f"{res.mesh.volume / 1000:.2f}" in app.controls.measure.content


def _ring_feret(live):
    """Largest distance between two points of the drawn maximum-diameter section, mm."""
    from scipy.spatial.distance import pdist

    nodes = live.server.scene._handle_from_node_name
    ring = nodes["/aaa/max_section"].points.reshape(-1, 3).astype(np.float64)
    return float(pdist(ring).max()), nodes


def test_session_surface_finished_and_aaa_shown(app):
    """A re-run runs the pipeline's stages after marching cubes: finish_surface, and measure_aaa
    (the sample is an AAA); the scene draws the centreline and the maximum-diameter section."""
    from test_surface_aaa import _true_max_section

    from organlab.surface import mesh_quality
    from organlab.synthetic import AAAPhantom

    res = app.result
    assert res.raw_mesh is not None and res.mesh.is_watertight
    # the marching-cubes slivers are gone (raw: measured < 1 degree; finished: 20+)
    assert mesh_quality(res.raw_mesh)["min_angle_deg"] < 1.0 < 20.0 <= mesh_quality(res.mesh)["min_angle_deg"]
    assert abs(res.mesh.volume / res.raw_mesh.volume - 1) < 0.005  # finish_surface keeps the volume
    a = res.aaa
    assert a is not None and res.aaa_error is None
    feret, nodes = _ring_feret(app.live)
    assert {"/aaa/centreline", "/aaa/max_section", "/aaa/max_disc", "/aaa/max_diameter", "/aaa/label"} <= set(nodes)
    line = nodes["/aaa/centreline"].points
    np.testing.assert_allclose(line[:, 0], a.centreline[:-1], atol=1e-3)  # float32 in the scene
    np.testing.assert_allclose(line[-1, 1], a.centreline[-1], atol=1e-3)
    assert abs(feret - a.max_diameter_mm) < 0.01
    d = nodes["/aaa/max_diameter"].points[0]
    assert abs(np.linalg.norm(d[1] - d[0]) - a.max_diameter_mm) < 0.01
    # against the phantom's exact geometry (54.60 mm): 12 views at 2 mm, measured 55.15 mm (+0.55)
    true_d, _ = _true_max_section(AAAPhantom())
    assert abs(feret - true_d) < 1.5
    assert f"{a.max_diameter_mm:.1f} mm" in nodes["/aaa/label"].text
    assert f"**AAA max diameter** {a.max_diameter_mm:.1f} mm" in app.controls.measure.content
    assert app.live._handles["mesh"].opacity == 0.5  # translucent: the centreline inside is seen
    app.controls.aaa_box.value = False  # hidden with its checkbox, the mesh opaque again
    assert not app.live._handles["aaa"].visible and app.live._handles["mesh"].opacity is None
    app.controls.aaa_box.value = True
    assert app.live._handles["aaa"].visible and app.live._handles["mesh"].opacity == 0.5


def test_agreement_drops_for_a_wrong_camera(app):
    from organlab.agreement import view_agreement

    res = app.result
    cams = list(app.cameras)
    cams[0] = cams[6]  # view 0 paired with the camera of another view
    ag = np.array([v["iou"] for v in view_agreement(res.mesh, cams, res.reconstruction.silhouettes, voxel_size=2.0).views])
    assert ag[0] < res.agreement[0] - 0.05
    np.testing.assert_allclose(ag[1:], res.agreement[1:])


def test_threshold_rerun_and_cancel(app):
    before = app.result
    # a much higher threshold loses the specimen's faint parts: a smaller hull
    # (measured 62 % of the reference volume, against 101 % automatic)
    g = app.rerun(threshold=45.0)
    assert app.wait(g, timeout=120) and not app.errors
    assert app.result.generation == g and app.result.settings.threshold == 45.0
    assert app.result.mesh.volume < before.mesh.volume
    assert app.status.startswith("run 1: done in")  # the first change is run 1, whatever the generation
    # the run's warnings (views whose silhouettes the smaller model leaves unexplained) are in the panel
    warnings = app.result.report["warnings"]
    assert warnings and not before.report["warnings"], (warnings, before.report["warnings"])
    assert "**Warnings**" in app.controls.measure.content and warnings[0] in app.controls.measure.content
    # a newer request supersedes an older one still running: only the newest is shown
    g1 = app.rerun(threshold=None, voxel_size=1.0)
    g2 = app.rerun(voxel_size=2.0)
    assert g2 == g1 + 1 and app.wait(g2, timeout=120)
    assert app.result.generation == g2 and app.result.grid.voxel_size == 2.0
    assert app.worker.finished == g2
    assert app.status.startswith("run 2: done in")  # the superseded request took no number
    assert "**Warnings**" not in app.controls.measure.content
    np.testing.assert_allclose(app.result.mesh.volume, before.mesh.volume, rtol=1e-9)


def test_carve_by_view_display(app):
    c = app.controls
    views = app.carving_views()
    np.testing.assert_array_equal(views == -1, carve(app.result.masks, app.cameras, app.result.grid))
    c.carve_show.value = True
    c._carve_display()
    shown = app.live._handles["carved"].points
    from organlab.viewer._scene import near_hull

    near = near_hull(views, app.result.occupancy, 2)
    assert len(shown) == near.sum() > 0
    c.carve_step.value = 3
    c._carve_display()
    assert len(app.live._handles["carved"].points) == (near & (views == 3)).sum()
    assert int(c.view.value) == 3  # stepping selects that view
    c.carve_show.value = False
    c._carve_display()
    assert not app.live._handles["carved"].visible


def test_select_view_overlay_and_roi_readout(app):
    from organlab.viewer._scene import roi_stats

    img = app.controls.select(4)
    sil = app.result.masks[4]
    d = img.astype(int) - app.images[4]
    outline = (img == (230, 40, 40)).all(axis=2)  # the hull's outline, drawn red
    # silhouette tinted green, the rest of the photo untouched
    assert d[sil & ~outline][:, 1].mean() > 20 + d[sil & ~outline][:, 0].mean()
    assert not d[~sil & ~outline].any()
    # the outline runs along the silhouette's edge (agreement ~0.98)
    assert 500 < outline.sum() < 20000
    from scipy import ndimage

    edge = ndimage.binary_dilation(sil, iterations=3) & ~ndimage.binary_erosion(sil, iterations=3)
    assert (outline & edge).sum() > 0.9 * outline.sum()
    assert "0.9" in app.controls.view_info.content
    lo, hi = app.controls.roi()
    n, b = roi_stats(lo, hi, 2.0)
    assert n == VoxelGrid.from_roi(lo, hi, 2.0).n_voxels == 70 * 70 * 100
    assert f"{n:,} voxels" in app.controls.roi_info.content


def test_result_folder(sample, tmp_path):
    from organlab.pipeline import reconstruct, write_outputs
    from organlab.viewer import SessionViewer

    rec = reconstruct(sample, voxel_size=2.0)
    write_outputs(rec, tmp_path / "out")
    v = SessionViewer(sample, result=tmp_path / "out", views=[0, 9, 18, 27], port=0)
    try:
        assert v.result is not None and v.worker.generation == 0  # nothing re-computed
        np.testing.assert_allclose(v.result.mesh.volume, rec.mesh.volume, rtol=1e-6)
        assert len(v.live._handles["voxels"].points) > 0
        assert v.result.agreement.min() > 0.95
        # the report has AAA measures: centreline and maximum section drawn, measured again from voxels.npz
        feret, nodes = _ring_feret(v.live)
        assert abs(feret - rec.report["aaa"]["max_diameter_mm"]) < 1.0  # same volume, same function: measured 0.0 mm
        np.testing.assert_allclose(nodes["/aaa/centreline"].points[:, 0], rec.aaa.centreline[:-1], atol=0.01)
    finally:
        v.stop()


def test_cli_view_bad_input(tmp_path, capsys, sample, monkeypatch):
    import json

    from organlab.cli import main
    from organlab.viewer import _app

    def no_server(**_kw):
        raise AssertionError("the server started before the input was checked")

    monkeypatch.setattr(_app, "LiveView", no_server)
    other = tmp_path / "other"
    other.mkdir()
    for name in ("voxels.npz", "mesh.ply"):
        (other / name).write_bytes(b"")
    (other / "report.json").write_text(json.dumps({"session": "dino", "views": [{"image": "views/a.png"}] * 3}))
    (tmp_path / "afile").write_text("x")
    cases = [
        (["view", str(tmp_path / "nope")], "session folder does not exist"),
        (["view", str(tmp_path / "afile")], "is a file, not a session folder"),
        (["view", str(sample), "--result", str(tmp_path / "nonexist")], "result folder does not exist"),
        (["view", str(sample), "--result", str(tmp_path / "afile")], "is a file, not a result folder"),
        (["view", str(sample), "--result", str(tmp_path)], "voxels.npz: missing"),
        (["view", str(sample), "--result", str(other)], "made from session 'dino' (3 views), not from"),
    ]
    for argv, says in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("organlab: error:") and says in err[0], (argv, err)


def test_thesis_hull_and_coloring_reruns(app):
    from organlab.viewer._scene import surface_voxels

    from organlab.engine import HULL_METHODS, METHODS

    base = app.result
    assert base.settings.hull == "subvoxel" and base.settings.method == "hull"
    # the dropdowns offer the engine's methods (its one list, not a copy kept by the GUI)
    assert tuple(app.controls.method.options) == METHODS and tuple(app.controls.hull.options) == HULL_METHODS
    g = app.rerun(hull="thesis")
    assert app.wait(g, timeout=120) and not app.errors
    res = app.result
    np.testing.assert_array_equal(res.occupancy, carve(res.masks, app.cameras, res.grid))
    g = app.rerun(hull="subvoxel", method="coloring")
    assert app.wait(g, timeout=300) and not app.errors
    res = app.result
    assert res.colors is not None and res.mesh.vertex_colors is not None
    # the colour slider shows the automatic threshold colouring measured, without re-running
    c = app.controls
    assert res.settings.color_threshold is None and res.color_threshold > 0
    assert c.color_auto.value is True and abs(c.color_threshold.value - res.color_threshold) <= 0.25
    assert app.worker.generation == g and f"{res.color_threshold:.1f} (automatic)" in c.measure.content
    assert not (res.occupancy & ~base.occupancy).any()  # colouring only carves the hull
    assert res.occupancy.sum() < base.occupancy.sum()
    # the voxels are shown in their colours
    np.testing.assert_array_equal(app.live._handles["voxels"].colors, res.colors[surface_voxels(res.occupancy)])
    assert type(app.live._handles["mesh"]).__name__ == "GlbHandle"  # mesh sent with vertex colours
    # moving the slider is a chosen threshold: a re-run at it, the automatic box unticked
    c.color_threshold.value = 40.0
    assert app.worker.generation == g + 1 and not c.color_auto.value
    assert app.wait(g + 1, timeout=300) and not app.errors
    assert app.result.settings.color_threshold == 40.0 and app.result.color_threshold == 40.0
    assert app.result.occupancy.sum() >= res.occupancy.sum()  # a higher threshold carves less
    g = app.rerun(method="hull")
    assert app.wait(g, timeout=120)


def test_photo_colour_slider_offers_the_ncc_gain(app):
    """The colour slider takes the range of the chosen method from the engine (photo: an NCC gain)."""
    from organlab.engine import color_threshold_range

    c = app.controls
    g = app.worker.generation
    c.method.value = "photo"  # grey levels -> NCC gain: back to automatic, the slider on the gain's range
    assert app.worker.generation == g + 1 and c.color_auto.value is True
    rng = color_threshold_range("photo")
    assert (c.color_threshold.min, c.color_threshold.max) == (rng.low, rng.high) == (0.05, 1.0)
    assert app.wait(g + 1, timeout=300) and not app.errors
    res = app.result
    assert res.settings.method == "photo" and res.settings.color_threshold is None
    assert res.color_threshold == rng.default and abs(c.color_threshold.value - rng.default) < 1e-9
    assert "0.25 NCC gain (automatic)" in c.measure.content
    c.color_threshold.value = 0.5  # a chosen gain is accepted by Settings (a grey-level 40 would not be)
    assert app.wait(g + 2, timeout=300) and not app.errors
    assert app.result.settings.color_threshold == 0.5 and not c.color_auto.value
    assert app.result.occupancy.sum() >= res.occupancy.sum()  # more evidence asked: never more carved
    c.method.value = "coloring"  # and back: the grey-level range
    assert (c.color_threshold.min, c.color_threshold.max) == (1.0, 60.0) and c.color_auto.value is True
    assert app.wait(g + 3, timeout=300) and not app.errors
    assert app.result.settings.color_threshold is None
    g = app.rerun(method="hull")
    assert app.wait(g, timeout=120)


def test_roi_box_readout_and_apply(app):
    c = app.controls
    c.roi_edit.value = True
    assert {"/roi", "/roi/box"} <= _nodes(app.live.server)
    c.roi_size.value = (100.0, 90.0, 180.0)
    assert tuple(app.live.server.scene._handle_from_node_name["/roi/box"].dimensions) == (100.0, 90.0, 180.0)
    assert f"{50 * 45 * 90:,} voxels at 2 mm" in c.roi_info.content
    g0 = app.worker.generation
    c.roi_apply.value = True  # as a click
    assert app.worker.generation == g0 + 1 and app.wait(timeout=120) and not app.errors
    assert app.result.grid.shape == (50, 45, 90)
    lo, hi = app.result.grid.bounds
    np.testing.assert_allclose(lo, [-50.0, -45.0, 10.0])
    c.roi_edit.value = False
    assert "/roi" not in _nodes(app.live.server)


def test_capture_listener_carves_as_the_table_turns(sample):
    """What organlab.capture's on_view(index, angle, image) feeds: the hull after
    the last view equals carve() of the same silhouettes."""
    from organlab import silhouette as S
    from organlab.camera import rot_z
    from organlab.pipeline import session_cameras
    from organlab.session import load_session
    from organlab.viewer import LiveView

    s = load_session(sample)
    cams = session_cameras(s)
    idx = list(range(0, 36, 4))
    cam0 = cams[0].with_pose(cams[0].R @ rot_z(-s.views[0].angle_deg), cams[0].t)  # the camera at table angle 0
    bg = S.background_model([s.read(p) for p in s.background_images])
    grid = VoxelGrid.from_roi(s.roi_min, s.roi_max, 4.0)
    live = LiveView(grid=grid, port=0)
    try:
        on_view = live.capture_listener(cam0, background=bg, threshold=20.0)
        masks = []
        for k, i in enumerate(idx):
            image = s.read(s.views[i].image)
            on_view(k, s.views[i].angle_deg, image)
            masks.append(S.silhouette(image, bg, threshold=20.0).mask)
            # the frustum stands where the session's camera of that view is
            np.testing.assert_allclose(live.cameras[-1].center, cams[i].center, atol=1e-6)
        from organlab.viewer._scene import surface_voxels

        hull = carve(masks, [cams[i] for i in idx], grid)
        assert len(live._handles["voxels"].points) == surface_voxels(hull).sum() > 0
    finally:
        live.stop()


def _on_cloth(sample, root, colours, backdrop):
    """The sample's specimen pasted on a cloth of a colour per view (PNG), no background frames, keyed
    against ``backdrop``; returns the loaded session."""
    import json
    import shutil
    from pathlib import Path

    import cv2

    from organlab.session import load_session
    from organlab.silhouette import silhouettes

    shutil.copytree(sample, root)
    s = load_session(root)
    rng = np.random.default_rng(5)
    doc = json.loads((root / "session.json").read_text())
    for k, (v, sil, entry) in enumerate(zip(s.views, silhouettes(s), doc["views"])):
        img = s.read(v.image).astype(float)
        a = sil.coverage[..., None]
        out = a * img + (1 - a) * (np.array(colours(k), float) + rng.normal(0, 2.0, img.shape))
        # PNG: JPEG's chroma subsampling would bleed the red into the blue by a pixel or two
        entry["image"] = f"views/{Path(v.image).stem}.png"
        cv2.imwrite(str(root / entry["image"]), np.clip(np.rint(out), 0, 255).astype(np.uint8)[:, :, ::-1])
    doc.update(background_images=[], backdrop=backdrop)
    (root / "session.json").write_text(json.dumps(doc))
    return load_session(root)


def _keyed_viewer(session, views):
    """A viewer of ``views`` of a backdrop session, after its first run, whose masks are the pipeline's."""
    from organlab.engine import Engine, Settings
    from organlab.viewer import SessionViewer

    # the pipeline's silhouettes of the same views: keyed, then (12 views of a backdrop session) the joint step
    expect = Engine(session, views=views).run(Settings(voxel_size=2.0), until="silhouettes").silhouettes
    v = SessionViewer(session, voxel_size=2.0, views=views, port=0, stream=False)
    assert v.wait(timeout=180), v.errors
    for j in range(len(views)):  # view for view
        np.testing.assert_array_equal(v.result.masks[j], expect[j].mask)
    return v


def test_backdrop_session_without_frames(sample, tmp_path):
    """A session keyed against a declared backdrop colour, with no background frames: the viewer keys
    its views (Delta E) as organlab reconstruct does, and re-keys at a chosen threshold."""
    keyed = _on_cloth(sample, tmp_path / "blue", lambda k: (20, 60, 200), {"color": [20, 60, 200]})
    v = _keyed_viewer(keyed, list(range(0, 36, 3)))
    try:
        assert v.threshold_units == "Delta E" and "Delta E" in v.controls.threshold._impl.props.hint
        ref = keyed.reference["volume_mm3"]
        # 12 views, 2 mm: measured 100.7 % (the frames session in the same viewer: 101 %)
        assert abs(v.result.mesh.volume / ref - 1) < 0.03
        g = v.rerun(threshold=60.0)  # Delta E 60: the specimen's darker parts are lost
        assert v.wait(g, timeout=120) and not v.errors
        assert v.result.mesh.volume < 0.97 * ref  # measured 93.8 %
    finally:
        v.stop()


def test_border_backdrop_estimated_over_every_view(sample, tmp_path):
    """'border': the viewer showing every third view estimates the cloth's colour over all views, as
    reconstruct does (here the cloth is lighter in the views it does not show)."""
    from organlab.silhouette import SilhouetteModel

    s = _on_cloth(sample, tmp_path / "cloth", lambda k: (20, 60, 200) if k % 3 == 0 else (45, 85, 170),
                  {"color": "border"})
    v = _keyed_viewer(s, list(range(0, 36, 3)))
    try:
        np.testing.assert_allclose(v.engine.silhouette_model.background, SilhouetteModel.from_session(s).background)
    finally:
        v.stop()


def test_going_back_to_a_recent_setting_runs_no_stage(app):
    """The slider back to a value shown a few requests ago: the engine takes that result's stages back
    (Engine.keep) and re-runs none; the same surface is shown again."""
    from organlab.viewer._app import RECENT

    def rerun(**kw):
        g = app.rerun(**kw)
        assert app.wait(g, timeout=120) and not app.errors and app.result.generation == g
        return app.result

    first = rerun(threshold=30.0)
    rerun(threshold=32.0)
    ran = dict(app.engine.computed)
    again = rerun(threshold=30.0)
    assert app.engine.computed == ran  # no stage ran
    assert again.mesh is first.mesh and again.aaa is first.aaa
    np.testing.assert_array_equal(app.live._handles["mesh"].vertices, first.mesh.vertices.astype(np.float32))
    np.testing.assert_array_equal(again.agreement, first.agreement)
    # only the RECENT newest settings are kept: after RECENT others, 30 is computed again
    for k in range(RECENT):
        rerun(threshold=34.0 + k)
    n = app.engine.computed["silhouettes"]
    rerun(threshold=30.0)
    assert app.engine.computed["silhouettes"] == n + 1
