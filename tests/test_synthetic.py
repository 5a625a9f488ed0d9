"""Tests of the synthetic session generator against independent truths."""

import json

import cv2
import numpy as np
import pytest

import organlab
from organlab import synthetic as syn
from organlab.camera import rot_z
from tests._shared_data import SAMPLE


@pytest.fixture(scope="module")
def cam():
    return syn.default_camera()


@pytest.fixture(scope="module")
def aaa():
    return syn.AAAPhantom()


@pytest.fixture(scope="module")
def grooved():
    return syn.GroovedSpecimen()


@pytest.fixture(scope="module")
def small_session(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "small"
    truth = syn.make_session(
        out,
        seed=3,
        image_size=(320, 240),
        n_views=4,
        n_intrinsic=3,
        n_turntable=2,
        n_background=2,
        supersample=2,
        board_supersample=2,
        noise_sigma=1.5,
    )
    return out, truth


# ----------------------------------------------------------------- camera
def test_default_camera_matches_the_brief(cam):
    K = cam.K
    assert 750 <= K[0, 0] <= 850 and 750 <= K[1, 1] <= 850
    assert 1 < np.hypot(K[0, 2] - 319.5, K[1, 2] - 239.5) < 10
    assert cam.dist[0] == pytest.approx(-0.3) and cam.dist[4] == 0 and cam.skew == 0
    c = cam.center
    assert 300 <= c[2] <= 380 and 450 <= np.hypot(c[0], c[1]) <= 550


def test_rays_reproject_through_the_distortion(cam):
    # the images are cast with Camera.rays: the rays must land back on their pixels
    rng = np.random.default_rng(0)
    px = rng.uniform([-0.5, -0.5], [639.5, 479.5], size=(500, 2))
    o, d = cam.rays(px)
    back = cam.project(o + 300.0 * d)
    assert np.max(np.abs(back - px)) < 1e-6


def test_cached_sample_rays_are_camera_rays():
    # the renderer's compiled undistortion must give Camera.rays' directions bit for bit (the images are
    # promised to be cast through Camera.rays); a coarse camera, 2 x 2 samples per pixel
    from organlab.synthetic import _render

    cam = syn.default_camera((160, 120))
    d = _render.camera_frame_rays(cam, 2)
    off = np.array([-0.25, 0.25])
    v, u, sv, su = np.meshgrid(np.arange(120), np.arange(160), off, off, indexing="ij")
    px = np.stack([(u + su).ravel(), (v + sv).ravel()], axis=1)
    assert np.array_equal(d, cam.with_pose(np.eye(3), np.zeros(3)).rays(px)[1])


@pytest.mark.parametrize("name", ["aaa", "aaa-11+branch", "grooved"])
def test_any_hit_is_where_the_first_hit_is_finite(name):
    # shadow and coverage rays ask only whether a ray hits: the same rays as _intersect's finite t,
    # here rays from random points around the solid (inside and outside it) in random directions
    spec = syn.make_specimen(name)
    moved = syn.Moved(spec, (3.0, -2.0), 25.0)
    rng = np.random.default_rng(5)
    lo, hi = spec.bounds
    o = rng.uniform(lo - 20.0, hi + 20.0, size=(4000, 3))
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for s in (spec, moved):
        hit = s._any_hit(o, d)
        assert 0.1 < hit.mean() < 0.9  # both kinds of rays are tried
        assert np.array_equal(hit, np.isfinite(s.intersect(o, d)[0]))


def test_roi_and_specimens_fit_in_every_view(cam, aaa, grooved):
    lo, hi = np.array(syn.DEFAULT_ROI["min"]), np.array(syn.DEFAULT_ROI["max"])
    box = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    # the edges of a box bend under distortion: sample them densely
    s = np.linspace(0, 1, 41)[:, None]
    pts = [box[i] + s * (box[j] - box[i]) for i in range(8) for j in range(8) if np.sum(box[i] != box[j]) == 1]
    pts = np.concatenate(pts)
    for spec in (aaa, grooved):
        assert np.all(spec.bounds[0] >= lo) and np.all(spec.bounds[1] <= hi)
    for a in range(0, 360, 10):
        uv, z = cam.at_table_angle(a).project(pts, return_depth=True)
        assert np.all(z > 0)
        assert np.all(uv >= 0) and np.all(uv[:, 0] <= 639) and np.all(uv[:, 1] <= 479), a


# ------------------------------------------------------------- specimens
@pytest.mark.parametrize("name", ["aaa", "grooved"])
def test_exact_volume_matches_a_dense_grid_count(name, aaa, grooved):
    spec = aaa if name == "aaa" else grooved
    # the quadrature has converged (Gauss-Legendre in z, periodic trapezoid in phi)
    assert spec.star._volume(96, 4096) == pytest.approx(spec.star.volume, rel=1e-10)
    h = 0.7
    lo, hi = spec.bounds
    xs, ys, zs = (np.arange(lo[i] + h / 2, hi[i], h) for i in range(3))
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    count = 0
    for z in zs:
        count += np.count_nonzero(spec.inside(np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], axis=1)))
    assert count * h**3 == pytest.approx(spec.volume, rel=5e-3)


def test_aaa_shape_is_as_specified(aaa):
    assert 150e3 <= aaa.volume <= 200e3
    assert 150 <= aaa.height <= 180
    phi = np.linspace(0, np.pi, 360, endpoint=False)
    z = np.linspace(aaa.z_b, aaa.height, 300)
    r1 = aaa.star.radius(phi[None, :], z[:, None])
    r2 = aaa.star.radius(phi[None, :] + np.pi, z[:, None])
    diam = r1 + r2
    assert 50 <= diam.max() <= 56  # aneurysm
    assert 22 <= diam[-1].mean() <= 26  # aorta at the top
    # iliac legs: horizontal sections at z_b inside the aorta, disjoint, volume formula
    for leg in aaa.legs:
        theta = np.arccos(-leg.axis[2])
        assert leg.volume == pytest.approx(np.pi * leg.radius**2 * aaa.z_b / np.cos(theta))
    u = np.linspace(0, 2 * np.pi, 400)
    p0 = aaa.legs[0].point
    sec = aaa.legs[0]
    A = sec.radius / -sec.axis[2]
    e = p0[:2] / np.linalg.norm(p0[:2])
    ring = p0[:2] + A * np.cos(u)[:, None] * e + sec.radius * np.sin(u)[:, None] * np.array([-e[1], e[0]])
    r_ring = np.hypot(ring[:, 0], ring[:, 1])
    assert np.all(r_ring < aaa.star.radius(np.arctan2(ring[:, 1], ring[:, 0]), np.full(len(u), aaa.z_b)))
    assert np.min(ring @ e) > 0  # the other leg's section is the mirror image: disjoint


@pytest.mark.parametrize("make", [syn.AAAPhantom, syn.GroovedSpecimen, lambda: syn.Sphere((5, -3, 40), 25), lambda: syn.Cylinder((4, 2), 20, 0, 60)])
def test_ray_hits_lie_on_the_surface(make, cam):
    spec = make()
    rng = np.random.default_rng(1)
    cam_a = cam.at_table_angle(37)
    target = rng.uniform(spec.bounds[0], spec.bounds[1], size=(3000, 3))
    o = np.broadcast_to(cam_a.center, target.shape)
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, n = spec.intersect(o, d)
    hit = np.isfinite(t)
    assert hit.sum() > 300
    p = o[hit] + t[hit, None] * d[hit]
    eps = 2e-3
    assert np.all(spec.inside(p + eps * d[hit]))
    assert not np.any(spec.inside(p - eps * d[hit]))
    assert np.allclose(np.linalg.norm(n[hit], axis=1), 1)
    assert np.all(np.sum(n[hit] * d[hit], axis=1) < 0)  # outward normals face the camera
    # a miss never passes through the solid: sample along the missing rays
    miss = np.flatnonzero(~hit)[:300]
    s = np.linspace(0, 1200, 2401)
    pts = o[miss][:, None, :] + s[None, :, None] * d[miss][:, None, :]
    assert not np.any(spec.inside(pts.reshape(-1, 3)))


def test_simple_shape_volumes():
    assert syn.Sphere((0, 0, 30), 20).volume == pytest.approx(4 / 3 * np.pi * 8000)
    assert syn.Cylinder((1, 2), 10, 0, 50).volume == pytest.approx(np.pi * 100 * 50)
    assert syn.Sphere((0, 0, 30), 20).inside([[0, 0, 49.9], [0, 0, 50.1]]).tolist() == [True, False]
    with pytest.raises(ValueError, match="radius"):
        syn.Sphere((0, 0, 0), -1)
    with pytest.raises(ValueError, match="unknown specimen"):
        syn.make_specimen("kidney")


def test_grooves_are_hidden_from_every_silhouette(cam, grooved):
    # points deep inside the pockets (outside the solid) project inside the silhouette in all 36 views
    spec = grooved
    pts = []
    for mu in spec.groove_angles:
        for z in np.linspace(35, 55, 5):
            r_in = spec.star.radius(mu, z)
            r_out = spec.star.radius(mu, 100.0)  # the section without the dent (above the pockets)
            assert r_out - r_in > 8
            for r in np.linspace(r_in + 0.3, r_in + 0.6 * (r_out - r_in), 5):  # the inner 60 % of the dent
                pts.append([r * np.cos(mu), r * np.sin(mu), z])
    pts = np.array(pts)
    assert not np.any(spec.inside(pts))
    for a in range(0, 360, 10):
        c = cam.at_table_angle(a)
        d = pts - c.center
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        t, _ = spec.intersect(np.broadcast_to(c.center, d.shape), d)
        assert np.all(np.isfinite(t)), a


def test_albedo_is_textured_reddish_and_distinct(aaa):
    rng = np.random.default_rng(2)
    p = rng.uniform(-40, 40, size=(20000, 3)) + [0, 0, 80]
    col = aaa.albedo(p)
    grey = col @ [0.299, 0.587, 0.114]
    assert 55 <= np.percentile(grey, 1) and np.percentile(grey, 99) <= 225
    assert np.std(grey) > 25  # high contrast
    assert np.all(col[:, 0] - col[:, 1] > 25)  # chroma: never grey like the plate


# ------------------------------------------------------------------ images
def _detect(img):
    ok, corners = cv2.findChessboardCornersSB(img, (9, 6), flags=cv2.CALIB_CB_ACCURACY)
    assert ok
    return corners.reshape(-1, 2)


def _rms_to(corners, uv):
    d = np.linalg.norm(corners[:, None, :] - uv[None, :, :], axis=2)
    nearest = d.min(axis=1)
    assert len(set(d.argmin(axis=1))) == len(uv)
    return np.sqrt(np.mean(nearest**2))


def test_rendered_board_corners_are_where_the_camera_projects_them(cam):
    cam0 = cam.with_pose(np.eye(3), np.zeros(3))
    poses = syn.intrinsic_board_poses(cam, 3, seed=5)
    for k, (R, t) in enumerate(poses):
        img = syn.render_board(cam0, R, t, supersample=2, table=False, noise_sigma=1.0, seed=k)
        uv = cam0.project(syn.board_object_points() @ R.T + t)
        assert _rms_to(_detect(img), uv) < 0.1


def test_intrinsic_poses_are_varied_and_fully_visible(cam):
    poses = syn.intrinsic_board_poses(cam, 15, seed=0)
    cam0 = cam.with_pose(np.eye(3), np.zeros(3))
    tilts, centres = [], []
    for R, t in poses:
        uv = cam0.project(syn.board_object_points() @ R.T + t)
        assert np.all(uv > 10) and np.all(uv[:, 0] < 630) and np.all(uv[:, 1] < 470)
        tilts.append(np.degrees(np.arccos(-R[2, 2])))
        centres.append(uv.mean(axis=0))
    assert max(tilts) > 30 and max(tilts) <= 45.01
    centres = np.array(centres)
    assert np.ptp(centres[:, 0]) > 100 and np.ptp(centres[:, 1]) > 60
    assert len(poses) == 15 and syn.intrinsic_board_poses(cam, 15, seed=0)[7][1].tolist() == poses[7][1].tolist()


def test_turntable_board_orientation_rule(cam):
    """At angle 0 the board's long side runs along +X from its black-corner end (spec's world frame)."""
    R, t = syn.turntable_board_pose()
    img = syn.render_board(cam, R, t, supersample=2, table=True, noise_sigma=1.0, seed=0)
    c = _detect(img).reshape(6, 9, 2)  # detector order, whatever it is
    # back-project the detected corners onto the table plane z = 0 with the true camera
    o, d = cam.rays(c.reshape(-1, 2))
    X = (o - (o[:, 2] / d[:, 2])[:, None] * d).reshape(6, 9, 3)
    long_dir = X[:, -1] - X[:, 0]  # along inner_corners[0]
    assert np.all(np.abs(long_dir[:, 1]) < 0.02 * np.abs(long_dir[:, 0]))  # the long side is along X
    img_f = img.astype(float)

    def corner_square(r, col, dr, dc):
        # centre of the corner square beyond corner (r, col), in the table plane, seen in the image
        p = X[r, col] + 0.5 * (X[r, col] - X[r + dr, col + dc])
        u, v = cam.project(p)[0]
        return img_f[int(round(v)), int(round(u))]

    end0 = [corner_square(0, 0, 1, 1), corner_square(5, 0, -1, 1)]
    end1 = [corner_square(0, 8, 1, -1), corner_square(5, 8, -1, -1)]
    black_end, white_end = (X[:, 0], X[:, -1]) if max(end0) < 100 < min(end1) else (X[:, -1], X[:, 0])
    assert max(end0 + end1) > 150 and min(end0 + end1) < 60
    assert black_end[:, 0].mean() < white_end[:, 0].mean() - 100
    # and that agrees with the object points the calibration uses
    Xw = syn.turntable_board_points(0).reshape(6, 9, 3)
    assert np.allclose(Xw[:, 0, 0].mean(), black_end[:, 0].mean(), atol=0.5)
    assert np.allclose(syn.turntable_board_points(30), syn.turntable_board_points(0) @ rot_z(30).T)


def test_turntable_board_corners_match(cam):
    R, t = syn.turntable_board_pose()
    for a in (60, 140):
        c = cam.at_table_angle(a)
        img = syn.render_board(c, R, t, supersample=2, table=True, noise_sigma=1.0, seed=a)
        uv = c.project(syn.turntable_board_points(0))
        assert _rms_to(_detect(img), uv) < 0.15


def test_mask_area_matches_the_projected_outline_of_a_sphere():
    # silhouette of a ball = projection (with distortion) of its tangent circle
    sph = syn.Sphere((20.0, -15.0, 60.0), 30.0)
    c = syn.default_camera((320, 240)).at_table_angle(25)
    m = syn.render_masks(sph, c, supersample=4)
    assert m.dtype == np.float32 and m.shape == (240, 320) and m.min() == 0 and m.max() == 1
    v = sph.center - c.center
    L = np.linalg.norm(v)
    w = v / L
    a = np.cross(w, [0, 0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(w, a)
    rt = sph.radius * np.sqrt(L**2 - sph.radius**2) / L
    s = np.linspace(0, 2 * np.pi, 4000, endpoint=False)
    ring = c.center + (L - sph.radius**2 / L) * w + rt * (np.cos(s)[:, None] * a + np.sin(s)[:, None] * b)
    uv = c.project(ring)
    area = 0.5 * abs(np.dot(uv[:, 0], np.roll(uv[:, 1], 1)) - np.dot(uv[:, 1], np.roll(uv[:, 0], 1)))
    assert m.sum() == pytest.approx(area, rel=2e-3)
    centroid = np.array([np.sum(m * np.arange(320)[None, :]), np.sum(m * np.arange(240)[:, None])]) / m.sum()
    assert np.allclose(centroid, uv.mean(axis=0), atol=0.5)


def test_background_is_the_same_at_every_table_angle(aaa):
    from organlab.synthetic import _render

    cam = syn.default_camera((320, 240))
    _render._BG_CACHE.clear()
    b0 = syn.render_view(None, cam.with_pose(cam.R, cam.t), supersample=2)
    _render._BG_CACHE.clear()
    b1 = syn.render_view(None, cam.at_table_angle(130), supersample=2)
    assert np.abs(b0.astype(int) - b1).max() <= 1
    v = syn.render_view(aaa, cam.at_table_angle(130), supersample=2)
    cov = syn.render_masks(aaa, cam.at_table_angle(130), supersample=2)
    near = cv2.dilate((cov > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert np.array_equal(v[~near], b1[~near])
    # the specimen stands out from the plate and backdrop
    core = cv2.erode((cov == 1).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    assert core.sum() > 2000
    assert np.all(np.abs(v[core].astype(int) - b1[core]).max(axis=1) > 20)


# ---------------------------------------------------------------- sessions
def test_session_loads_and_matches_truth(small_session):
    out, truth = small_session
    s = organlab.load_session(out)
    assert s.image_size == (320, 240)
    assert len(s.views) == 4 and len(s.intrinsic_images) == 3 and len(s.turntable_images) == 2
    assert len(s.background_images) == 2
    assert s.reference["volume_mm3"] == pytest.approx(syn.AAAPhantom().volume, rel=1e-12)
    saved = json.loads((out / "truth.json").read_text())
    assert saved["volume_mm3"] == s.reference["volume_mm3"]
    true_cam = syn.default_camera((320, 240))
    assert np.allclose(s.camera["K"], true_cam.K) and np.allclose(saved["camera"]["R_cam"], true_cam.R)
    for v, tv in zip(s.views, saved["views"]):
        c = true_cam.at_table_angle(v.angle_deg)
        assert np.allclose(v.pose[0], c.R) and np.allclose(v.pose[1], c.t)
        assert np.allclose(tv["R"], c.R)
    img = s.read(s.views[1].image)
    assert img.shape == (240, 320, 3)
    grey = s.read(s.intrinsic_images[0], grey=True)
    assert grey.ndim == 2
    # noise is independent per frame, with the requested sigma
    b = [s.read(p).astype(float) for p in s.background_images]
    assert np.std(b[0] - b[1]) / np.sqrt(2) == pytest.approx(1.5, rel=0.1)


def test_session_is_deterministic_from_the_seed(small_session, tmp_path):
    out, _ = small_session
    kw = dict(image_size=(320, 240), n_views=4, n_intrinsic=3, n_turntable=2, n_background=2, supersample=2, board_supersample=2, noise_sigma=1.5)
    again = tmp_path / "again"
    syn.make_session(again, seed=3, **kw)
    for p in sorted(out.rglob("*.png")):
        q = again / p.relative_to(out)
        assert p.read_bytes() == q.read_bytes(), p.name
    other = tmp_path / "other"
    syn.make_session(other, seed=4, views_only=True, **{**kw, "n_background": 1, "n_views": 1})
    assert (other / "views/000.png").read_bytes() != (out / "views/000.png").read_bytes()
    assert not (other / "calibration").exists()


def test_session_options_are_checked(tmp_path):
    with pytest.raises(ValueError, match="include_camera"):
        syn.make_session(tmp_path / "x", views_only=True, include_camera=False)
    with pytest.raises(ValueError, match="n_views"):
        syn.make_session(tmp_path / "x", n_views=-1)
    with pytest.raises(ValueError, match="view_format"):
        syn.make_session(tmp_path / "x", view_format="bmp", n_views=0, n_intrinsic=0, n_turntable=0, n_background=0)


def test_committed_sample_session_is_valid_and_small():

    root = SAMPLE
    if not (root / "session.json").is_file():
        pytest.skip("sample session not generated (make sample)")
    s = organlab.load_session(root)  # opens every image
    truth = json.loads((root / "truth.json").read_text())
    assert len(s.views) == 36 and len(s.intrinsic_images) == 15 and len(s.turntable_images) == 10
    assert len(s.background_images) == 20
    assert s.reference["volume_mm3"] == pytest.approx(syn.AAAPhantom().volume, rel=1e-12)
    assert truth["volume_mm3"] == s.reference["volume_mm3"]
    assert np.allclose(truth["camera"]["K"], syn.default_camera().K)
    # the sample calibrates from its images: no given camera or poses, the truth is in truth.json
    assert s.camera is None and all(v.pose is None for v in s.views)
    assert np.allclose(truth["views"][5]["R"], syn.default_camera().at_table_angle(50).R)
    size = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    assert size < 15e6


@pytest.mark.slow
def test_every_intrinsic_board_is_detected(cam):
    cam0 = cam.with_pose(np.eye(3), np.zeros(3))
    for k, (R, t) in enumerate(syn.intrinsic_board_poses(cam, 15, seed=0)):
        img = syn.render_board(cam0, R, t, supersample=2, table=False, noise_sigma=1.0, seed=k)
        uv = cam0.project(syn.board_object_points() @ R.T + t)
        assert _rms_to(_detect(img), uv) < 0.12, k


def test_cli_refuses_a_folder_that_is_not_empty_without_force(tmp_path, capsys):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(SystemExit) as e:
        syn.main([str(out), "--small"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "not empty" in err and "--force" in err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]  # nothing written
    assert syn.main([str(out), "--small", "--force", "--seed", "2"]) == 0
    assert (out / "notes.txt").read_text() == "mine"  # --force replaces only what the generator writes
    assert len(json.loads((out / "session.json").read_text())["views"]) == 12
