"""End to end: a rendered session through the pipeline and the CLI."""

import json
import shutil

import numpy as np
import pytest

from organlab import load_session
from organlab.cli import main
from organlab.errors import SessionError
from organlab.pipeline import reconstruct, session_cameras, write_outputs
from organlab.surface import read_ply
from organlab.synthetic import make_session
from tests._shared_data import posed_session_12

SPEC_REPORT_KEYS = {"volume_mm3", "mesh_volume_mm3", "mesh_area_mm2", "watertight", "voxel_size_mm", "timings_s", "views", "camera"}


@pytest.fixture(scope="module")
def posed(tmp_path_factory):
    """Small session with the true camera and poses given (no calibration needed), read-only: made once per run
    and shared with test_robustness.py (tests/_shared_data.posed_session_12)."""
    root = posed_session_12(tmp_path_factory)
    return root, json.loads((root / "truth.json").read_text())


@pytest.fixture(scope="module")
def posed_result(posed):
    return reconstruct(posed[0], voxel_size=2.0)


def test_report_follows_the_spec(posed, posed_result, tmp_path):
    root, truth = posed
    paths = write_outputs(posed_result, tmp_path / "out")
    report = json.loads(paths["report"].read_text())
    assert SPEC_REPORT_KEYS <= report.keys()
    assert set(report["timings_s"]) == {"silhouettes", "carving", "surface"}
    assert report["watertight"] is True and report["voxel_size_mm"] == 2.0
    assert len(report["views"]) == 12 and {"angle_deg", "R", "t"} <= report["views"][0].keys()
    np.testing.assert_allclose(report["camera"]["K"], truth["camera"]["K"])
    assert "rms_px" not in report["camera"]  # given, not calibrated
    with np.load(paths["voxels"], allow_pickle=False) as z:
        assert z["occupancy"].dtype == bool and z["occupancy"].shape == posed_result.grid.shape
        np.testing.assert_allclose(z["origin_mm"], [-69, -69, 1])  # roi min + half a voxel
        assert float(z["voxel_size_mm"]) == 2.0
        assert z["occupancy"].sum() * 8.0 == pytest.approx(report["volume_mm3"])
    mesh = read_ply(paths["ply"])
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(report["mesh_volume_mm3"], rel=1e-4)
    assert paths["stl"].stat().st_size == 84 + 50 * len(mesh.faces)


def test_volume_against_the_phantom(posed, posed_result):
    _, truth = posed
    true_volume = truth["volume_mm3"]
    # 12 views of 320x240 at 2 mm voxels: the sub-voxel surface is within 1.5 % of the truth
    assert posed_result.mesh.volume == pytest.approx(true_volume, rel=0.015)
    assert posed_result.report["mesh_volume_error_pct"] == pytest.approx(
        100 * (posed_result.mesh.volume - true_volume) / true_volume)
    # the model stands on z = 0 in the world frame, upright
    lo, hi = posed_result.mesh.bounds
    assert abs(lo[2] - 0.0) < 2.0 and hi[2] > 140


def test_thesis_hull_contains_the_subvoxel_hull(posed, posed_result):
    thesis = reconstruct(posed[0], voxel_size=2.0, hull="thesis")
    assert np.all(thesis.occupancy[posed_result.occupancy])
    # the 8-corner box test inflates the thin phantom by more than 10 %
    assert thesis.report["volume_mm3"] > 1.10 * posed_result.report["volume_mm3"]


def test_views_poses_are_the_given_ones(posed, posed_result):
    s = load_session(posed[0])
    for v, cam in zip(s.views, posed_result.cameras):
        np.testing.assert_allclose(cam.R, v.pose[0])
        np.testing.assert_allclose(cam.t, v.pose[1])


def test_cli_reconstruct_and_errors(posed, tmp_path, capsys):
    root, _ = posed
    out = tmp_path / "cli"
    assert main(["reconstruct", str(root), "--out", str(out), "--voxel-size", "4", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "mesh volume" in printed and "vs reference" in printed
    assert {p.name for p in out.iterdir()} == {"report.json", "voxels.npz", "mesh.ply", "mesh.stl"}

    bad = tmp_path / "bad"
    shutil.copytree(root, bad)
    (bad / "views/090.png").write_bytes(b"not a png")
    assert main(["reconstruct", str(bad), "--out", str(tmp_path / "o2"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("organlab: error: ") and "views[3].image" in err and "cannot be read" in err
    assert "Traceback" not in err and err.count("\n") == 1
    assert not (tmp_path / "o2").exists()

    with pytest.raises(SystemExit) as e:
        main(["reconstruct", str(root), "--out", str(out), "--voxel-size", "-1"])
    assert e.value.code == 2


@pytest.mark.slow
def test_calibrates_when_no_camera_is_given(tmp_path_factory, tmp_path):
    """No camera, no poses: reconstruct calibrates from the board images first.

    The session is the hostile tests' (tests/_hostile.py: seed 7, 320 x 240, 12 views, 8 intrinsic and 6
    turntable board images, no camera, no poses), rendered once per run and shared by the xdist workers,
    copied here without its calibration.json (it was a 640 x 480 session of its own, seed 5, 8 views:
    48 s CPU of rendering, nearly all of this test's 47 s in the suite).
    """
    from tests._hostile import small_calibrated

    root = tmp_path / "s"
    shutil.copytree(small_calibrated(tmp_path_factory), root,
                    ignore=shutil.ignore_patterns("calibration.json", "calibration_check"))
    truth = json.loads((root / "truth.json").read_text())
    rec = reconstruct(root, voxel_size=4.0)
    assert not (root / "calibration.json").exists()  # nothing is written into the session
    # measured: RMS 0.028 px, every camera centre 0.45 mm from the truth (bounds: a calibration that works)
    assert "calibration" in rec.report["timings_s"] and rec.report["camera"]["rms_px"] < 0.3
    true_centres = [np.asarray(v["center_mm"]) if "center_mm" in v else -np.asarray(v["R"]).T @ np.asarray(v["t"])
                    for v in truth["views"]]
    assert len(rec.cameras) == len(true_centres) == 12
    for cam, c in zip(rec.cameras, true_centres):
        assert np.linalg.norm(cam.center - c) < 2.0
    # saved into the session (as `organlab calibrate --in-place` does), a second run reuses it
    rec.calibration.save(root / "calibration.json")
    again = reconstruct(root, voxel_size=4.0)
    assert "calibration" not in again.report["timings_s"] and again.report["calibration"]["source"] == "reused, verified"
    np.testing.assert_allclose(again.cameras[0].K, rec.cameras[0].K)


def test_session_cameras_from_turntable(posed, tmp_path):
    s = load_session(posed[0])
    cams = session_cameras(s)
    R_cam, t_cam = cams[0].R, cams[0].t  # view 0 is at angle 0
    # the same session without camera and poses, with a calibration.json holding the truth
    root = tmp_path / "noposes"
    shutil.copytree(posed[0], root)
    raw = json.loads((root / "session.json").read_text())
    for v in raw["views"]:
        v.pop("pose")
    raw.pop("camera")
    (root / "session.json").write_text(json.dumps(raw))
    with pytest.raises(SessionError, match="camera: no intrinsics"):
        load_session(root)  # neither pose nor turntable calibration
    calib = {"camera": {"K": cams[0].K.tolist(), "dist": cams[0].dist.tolist(), "rms_px": 0.1},
             "turntable": {"R_cam": R_cam.tolist(), "t_cam": t_cam.tolist(), "rms_px": 0.1}}
    (root / "calibration.json").write_text(json.dumps(calib))
    s2 = load_session(root)
    for a, b in zip(session_cameras(s2), cams):
        np.testing.assert_allclose(a.R, b.R, atol=1e-9)
        np.testing.assert_allclose(a.t, b.t, atol=1e-9)


def test_given_masks_are_used_as_given(posed, posed_result, tmp_path):
    """Views with a `mask` skip background subtraction; no background frames are needed."""
    import cv2

    from organlab.synthetic import make_specimen, render_masks

    root = tmp_path / "masked"
    shutil.copytree(posed[0], root)
    raw = json.loads((root / "session.json").read_text())
    cams = posed_result.cameras
    coverage = render_masks(make_specimen("aaa"), cams, supersample=2)
    (root / "masks").mkdir()
    for i, (v, cov) in enumerate(zip(raw["views"], coverage)):
        cv2.imwrite(str(root / f"masks/{i:03d}.png"), np.where(cov >= 0.5, 255, 0).astype(np.uint8))
        v["mask"] = f"masks/{i:03d}.png"
    raw.pop("background_images")
    (root / "session.json").write_text(json.dumps(raw))
    rec = reconstruct(root, voxel_size=2.0)
    assert all(s.source == "given" and s.threshold is None for s in rec.silhouettes)
    for s, cov in zip(rec.silhouettes, coverage):
        np.testing.assert_array_equal(s.mask, cov >= 0.5)
    # the hull of the true silhouettes contains the phantom; 12 views of 320 x 240 px
    # leave it a few percent larger (measured +3.4 % with binary masks at 2 mm)
    true_volume = posed[1]["volume_mm3"]
    assert true_volume < rec.mesh.volume < 1.05 * true_volume
    assert rec.report["views"][0]["silhouette_source"] == "given"


@pytest.mark.slow
def test_coloring_method_writes_colors_and_carves_hidden_grooves(tmp_path):
    """--method coloring: colours in voxels.npz and mesh.ply; the grooves no silhouette shows shrink."""
    from organlab.synthetic import make_specimen

    root = tmp_path / "g"
    make_session(root, specimen="grooved", image_size=(320, 240), n_views=18, n_background=4, views_only=True, seed=2)
    spec = make_specimen("grooved")
    hull = reconstruct(root, voxel_size=2.0)
    col = reconstruct(root, voxel_size=2.0, method="coloring")
    assert "coloring" in col.report["timings_s"] and col.report["method"] == "coloring"
    c = col.report["coloring"]  # the colour threshold used and what colouring removed from the hull
    assert c["automatic"] is True and c["threshold"] > 0
    assert c["removed_volume_mm3"] == pytest.approx(hull.grid.volume_of(hull.occupancy) - col.grid.volume_of(col.occupancy))
    inside = spec.inside(hull.grid.centers()).reshape(hull.grid.shape)
    excess_hull = (hull.occupancy & ~inside).sum()
    excess_col = (col.occupancy & ~inside).sum()
    # measured with the fixed threshold 18 tuned on this specimen: 2377 -> 1286 excess voxels, 2.6 % of
    # the true voxels lost; with the pipeline's automatic threshold and shading-robust measure
    # (issue 13: no cliff on scenes the defaults never saw): 2377 -> 1862, 0.04 % lost besides the
    # 2.1 % the sub-voxel hull already misses at 2 mm (18 views of 320 x 240)
    assert excess_col < 0.85 * excess_hull
    lost_more = (~col.occupancy & inside).sum() - (~hull.occupancy & inside).sum()
    assert lost_more < 0.035 * inside.sum()
    assert abs(col.mesh.volume / spec.volume - 1) < abs(hull.mesh.volume / spec.volume - 1)
    assert col.mesh.is_watertight

    paths = write_outputs(col, tmp_path / "out")
    with np.load(paths["voxels"], allow_pickle=False) as z:
        assert z["colors"].shape == col.grid.shape + (3,) and z["colors"].dtype == np.uint8
    mesh = read_ply(paths["ply"])
    assert mesh.vertex_colors is not None and len(mesh.vertex_colors) == len(mesh.vertices)
    # vertex colours follow the specimen's texture (shading darkens them a little): measured 18 levels
    err = np.abs(mesh.vertex_colors.astype(float) - spec.albedo(mesh.vertices)).mean()
    assert err < 30


def test_cli_synth_writes_a_loadable_session(tmp_path, capsys):
    out = tmp_path / "small"
    assert main(["synth", str(out), "--small", "--specimen", "grooved", "--seed", "1"]) == 0
    assert "grooved volume" in capsys.readouterr().out
    s = load_session(out)
    assert s.image_size == (320, 240) and len(s.views) == 12
    truth = json.loads((out / "truth.json").read_text())
    assert s.reference["volume_mm3"] == truth["volume_mm3"]
