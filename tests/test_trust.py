"""Trustworthy runs (issue 15): views that disagree are flagged, bad input ends in
one line and exit 2 before the long work, outputs are replaced atomically.

Broken sessions are temporary copies of the sample session (calibrated once per
module: its calibration.json is copied into each broken copy, so only the views
differ).
"""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from organlab import load_session
from organlab.agreement import AGREEMENT_LIMIT
from organlab.cli import main
from organlab.errors import OrganlabError, SessionError
from organlab.pipeline import reconstruct, write_outputs
from organlab.preflight import bytes_per_voxel, check_grid_memory, check_output_dir, parse_memory
from tests._shared_data import SAMPLE, sample_calibrated


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A copy of the sample session with its calibration.json (computed once per run, shared with
    test_sweep.py: tests/_shared_data.sample_calibrated)."""
    return shutil.copytree(sample_calibrated(tmp_path_factory), tmp_path_factory.mktemp("trust") / "sample")


def _variant(calibrated, dest, edit):
    """A copy of the calibrated sample whose session.json is changed by ``edit(doc)``."""
    shutil.copytree(calibrated, dest, ignore=shutil.ignore_patterns("calibration_check"))
    doc = json.loads((dest / "session.json").read_text())
    edit(doc)
    (dest / "session.json").write_text(json.dumps(doc))
    return dest


def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert all(n in lines[0] for n in needles), lines[0]
    return lines[0]


# ------------------------------------------------------------------ view agreement
@pytest.fixture(scope="module")
def correct(calibrated):
    return reconstruct(calibrated, voxel_size=2.0)


@pytest.mark.slow
def test_the_correct_sample_raises_no_warning(correct):
    r = correct.report
    assert r.get("warnings") == []
    d = [v["agreement"]["disagreement_width_px"] for v in r["views"]]
    iou = [v["agreement"]["iou"] for v in r["views"]]
    # measured: largest disagreement 0.032 px of outline width (17 px of views/120.jpg, limit 0.05 px; issue 15's
    # measure on the finished surface: 0.0021 of the silhouette), smallest IoU 0.981
    assert max(d) < AGREEMENT_LIMIT and min(iou) > 0.975
    assert all(v["agreement"]["ok"] for v in r["views"])
    assert len(r["agreement"]["worst_views"]) == 3


@pytest.mark.slow
def test_a_mislabelled_view_is_flagged_and_strict_exits_2(calibrated, tmp_path, capsys):
    def edit(doc):
        for v in doc["views"]:
            if v["image"] == "views/050.jpg":
                v["angle_deg"] = 40.0

    root = _variant(calibrated, tmp_path / "angle", edit)
    out = tmp_path / "out"
    assert main(["reconstruct", str(root), "--out", str(out), "--voxel-size", "2", "--quiet", "--strict"]) == 2
    captured = capsys.readouterr()
    report = json.loads((out / "report.json").read_text())
    assert report["agreement"]["worst_views"][0] == "views/050.jpg"
    assert len(report["warnings"]) == 1 and "views/050.jpg" in report["warnings"][0]
    assert "wrong angle" in report["warnings"][0]
    # measured 0.098 px of outline width (53 px, limit 0.05 px); the other views stay within it (<= 0.041)
    bad = [v["image"] for v in report["views"] if not v["agreement"]["ok"]]
    assert bad == ["views/050.jpg"]
    assert "worst views       views/050.jpg" in captured.out
    # --strict: the warning is the one error line (exit 2), not a warning and then an error
    assert captured.err.startswith("organlab: error: --strict") and "views/050.jpg" in captured.err
    assert len(captured.err.strip().splitlines()) == 1
    # the angle it agrees best at (the hull of the other views turned about the table axis): its true 50
    # degrees (measured 49.5 at 2 mm, IoU 0.985 against 0.955 at the label; 50.0 at 1 mm)
    best = report["agreement"]["suggested_angles"]["views/050.jpg"]
    assert best["labelled"] == 40.0 and abs(best["best"] - 50.0) <= 1.0 and best["iou_best"] > best["iou_labelled"]
    assert "views/050.jpg agrees best at" in report["warnings"][0]


def test_no_angle_is_suggested_for_a_symmetric_specimen():
    """A ball looks the same at every angle: a view labelled 10 degrees off gets no suggestion."""
    from organlab.agreement import suggest_angles
    from organlab.grid import VoxelGrid
    from organlab.synthetic import Sphere, default_camera, render_masks

    ball = Sphere(center=(0.0, 0.0, 40.0), radius=25.0)
    table = default_camera((320, 240))
    angles = list(range(0, 360, 30))
    cov = render_masks(ball, [table.at_table_angle(a) for a in angles], supersample=2)
    labels = list(angles)
    labels[4] += 10.0
    grid = VoxelGrid.from_roi((-40, -40, 0), (40, 40, 80), 2.0)
    out = suggest_angles(table, labels, cov, [4], grid, names=[f"v{a}" for a in angles])
    # measured: IoU 0.982-0.989 over +-20 degrees (the 12-view hull's facets), no clear best
    assert out["v120"]["best"] is None and out["v120"]["labelled"] == 130.0


@pytest.mark.slow
def test_correct_labels_get_no_angle(tmp_path_factory, tmp_path):
    """A scene the suggestion was not set on: the phantom in hard mode at 320 x 240 (4:2:0 JPEG), correct
    labels, self-calibrated.  Every sixth view, looked at as if flagged: none is given another angle; the
    report suggests none either (its flagged views, if any, are JPEG blobs of 8-17 px on ~2 800 px
    silhouettes, not wrong labels).  The session (24 views, seed 6) is made once per run and shared with
    test_backdrop.py (tests/_shared_data.hard_session_24)."""
    from organlab.agreement import suggest_angles
    from tests._shared_data import hard_session_24

    root = shutil.copytree(hard_session_24(tmp_path_factory), tmp_path / "small")
    rec = reconstruct(root, voxel_size=2.0)
    angles = [v.angle_deg for v in rec.session.views]
    table = rec.calibration.turntable.camera
    for i in range(0, 24, 6):
        (s,) = suggest_angles(table, angles, rec.silhouettes, [i], rec.grid).values()
        assert s["best"] is None and s["iou_best"] - s["iou_labelled"] < 0.005, (i, s)
    assert all(s["best"] is None for s in rec.report["agreement"].get("suggested_angles", {}).values())
    assert all("agrees best" not in w for w in rec.report["warnings"])


@pytest.mark.slow
def test_identical_views_are_flagged(calibrated, tmp_path):
    def edit(doc):
        for v in doc["views"]:
            v["image"] = "views/000.jpg"

    rec = reconstruct(_variant(calibrated, tmp_path / "same", edit), voxel_size=2.0)
    bad = [v for v in rec.report["views"] if not v["agreement"]["ok"]]
    assert len(bad) > 30  # measured: 36 of 36, each about 0.08 of its silhouette unexplained
    assert "do not belong together" in rec.report["warnings"][0]


# ------------------------------------------------------------------ atomic outputs
@pytest.mark.slow
def test_an_interrupted_write_leaves_the_previous_result(correct, tmp_path, monkeypatch):
    import organlab.surface

    out = tmp_path / "out"
    write_outputs(correct, out)
    (out / "mesh.png").write_bytes(b"an earlier run's picture")
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def broken_stl(path, mesh):
        Path(path).write_bytes(b"solid half")
        raise KeyboardInterrupt  # Ctrl-C in the middle of the writes

    monkeypatch.setattr(organlab.surface, "write_stl", broken_stl)
    with pytest.raises(KeyboardInterrupt):
        write_outputs(correct, out)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temporary folder left
    with np.load(out / "voxels.npz") as z:
        assert np.array_equal(z["occupancy"], correct.occupancy)
    monkeypatch.undo()
    # a complete run replaces the folder as a whole: the earlier picture is gone
    paths = write_outputs(correct, out)
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in paths.values())
    assert json.loads((out / "report.json").read_text())["mesh_volume_mm3"] == pytest.approx(correct.mesh.volume)


def test_out_is_checked_before_any_work(tmp_path, capsys):
    f = tmp_path / "a_file"
    f.write_text("x")
    # --out a file: refused at once (the session does not even exist, so nothing was computed)
    assert main(["reconstruct", str(tmp_path / "nowhere"), "--out", str(f)]) == 2
    _one_line_error(capsys, str(f), "not a folder")
    other = tmp_path / "home"
    other.mkdir()
    (other / "thesis.docx").write_text("x")
    with pytest.raises(OrganlabError, match="did not write.*thesis.docx"):
        check_output_dir(other)
    assert check_output_dir(tmp_path / "new" / "out") == (tmp_path / "new" / "out").absolute()


# ------------------------------------------------------------------ numbers and memory
@pytest.mark.parametrize("value", ["inf", "nan", "-1", "0", "abc"])
def test_voxel_size_not_finite_positive_is_one_line(value, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["reconstruct", str(SAMPLE), "--out", str(tmp_path / "o"), "--voxel-size", value])
    assert e.value.code == 2
    _one_line_error(capsys, "--voxel-size")
    with pytest.raises(SessionError, match="^voxel_size must"):  # the library names its parameter, not the flag
        reconstruct(SAMPLE, voxel_size=float(value) if value != "abc" else value)


def test_a_grid_too_large_is_refused_with_the_voxel_size_that_fits(tmp_path, capsys):
    lo, hi = [-70.0, -70.0, 0.0], [70.0, 70.0, 200.0]  # the sample's roi
    limit = parse_memory("1G")
    assert limit == 1 << 30
    with pytest.raises(SessionError) as e:
        check_grid_memory(lo, hi, 0.05, max_memory=limit)
    suggested = float(str(e.value).split("--voxel-size ")[1].split()[0])
    assert check_grid_memory(lo, hi, suggested, max_memory=limit) <= limit
    with pytest.raises(SessionError):  # and it is (about) the smallest that fits
        check_grid_memory(lo, hi, 0.97 * suggested, max_memory=limit)
    # 0.05 mm on the sample: 3.1e10 voxels, refused before the silhouettes, in one line
    assert main(["reconstruct", str(SAMPLE), "--out", str(tmp_path / "o"), "--voxel-size", "0.05", "--quiet"]) == 2
    _one_line_error(capsys, "session.json", "--voxel-size")
    assert not (tmp_path / "o").exists() and not (SAMPLE / "calibration.json").exists()
    assert bytes_per_voxel(method="coloring") > bytes_per_voxel(method="hull")
    with pytest.raises(SessionError, match="max-memory"):
        parse_memory("lots")


# ------------------------------------------------------------------ rotations
def test_rotations_close_to_orthonormal_are_accepted_and_logged(tmp_path, capsys):
    from organlab.synthetic import with_true_cameras

    root = with_true_cameras(SAMPLE, tmp_path / "posed")
    doc = json.loads((root / "session.json").read_text())
    R0 = np.array(doc["views"][3]["pose"]["R"])
    # as printed with 7 digits by another tool: |R R^T - I| ~ 1e-6
    doc["views"][3]["pose"]["R"] = np.round(R0 * (1 + 1e-6 * np.array([[1, -1, 0.5], [0, 1, 1], [-1, 0, 1]])), 7).tolist()
    (root / "session.json").write_text(json.dumps(doc))
    s = load_session(root, check_images=False)
    R = s.views[3].pose[0]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R, R0, atol=3e-6)
    assert len(s.notes) == 1 and "views[3].pose.R re-orthonormalised" in s.notes[0]

    doc["views"][5]["pose"]["R"] = (np.array(doc["views"][5]["pose"]["R"]) * 1.001).tolist()  # 2e-3 off
    (root / "session.json").write_text(json.dumps(doc))
    assert main(["reconstruct", str(root), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    _one_line_error(capsys, "session.json", "views[5].pose.R", "not a rotation matrix")


def test_synth_refuses_a_non_empty_folder(tmp_path, capsys):
    (tmp_path / "session.json").write_text("{}")
    with pytest.raises(SystemExit) as e:
        main(["synth", str(tmp_path), "--small"])
    assert e.value.code == 2
    _one_line_error(capsys, str(tmp_path), "--force")
    assert (tmp_path / "session.json").read_text() == "{}"


# ------------------------------------------------------------------ organlab init
def test_init_writes_the_samples_session(tmp_path, capsys):
    """The sample's images without their session.json: init finds the same views, angles and board images."""
    root = tmp_path / "mine"
    shutil.copytree(SAMPLE, root, ignore=shutil.ignore_patterns("session.json", "truth.json", "calibration.json", "calibration_check"))
    assert main(["init", str(root), "--step", "10", "--roi=-70,-70,0,70,70,200"]) == 0
    assert "36 views, 20 background frames, 15 intrinsic and 10 turntable" in capsys.readouterr().out
    mine = load_session(root)  # validated images included
    ref = load_session(SAMPLE, check_images=False)
    assert [(v.image.name, v.angle_deg) for v in mine.views] == [(v.image.name, v.angle_deg) for v in ref.views]
    assert [(p.name, a) for p, a in mine.turntable_images] == [(p.name, a) for p, a in ref.turntable_images]
    assert [p.name for p in mine.intrinsic_images] == [p.name for p in ref.intrinsic_images]
    assert [p.name for p in mine.background_images] == [p.name for p in ref.background_images]
    assert mine.pattern == ref.pattern and mine.image_size == ref.image_size
    np.testing.assert_array_equal(mine.roi_max, ref.roi_max)
    # an existing session.json is kept; a flat folder of views without board images is refused with the fix
    assert main(["init", str(root), "--step", "10"]) == 2
    _one_line_error(capsys, "session.json", "--force")
    flat = tmp_path / "flat"
    flat.mkdir()
    for p in sorted((SAMPLE / "views").iterdir())[:3]:
        shutil.copy(p, flat / f"img{int(p.stem) // 10}.jpg")
    assert main(["init", str(flat), "--step", "-120"]) == 2
    # the fix named, not a session.json that init has just removed (issue 25)
    line = _one_line_error(capsys, str(flat), "no cameras", "--cameras FILE", "board images")
    assert "session.json" not in line
    assert not (flat / "session.json").exists()


def test_init_without_background_frames_keys_a_backdrop(tmp_path, capsys):
    """A rig with no frames of the empty scene: init declares a backdrop (the border's colour by default,
    or the one given) so the session loads and its views are keyed; a bad --backdrop is one line."""
    root = tmp_path / "cloth"
    shutil.copytree(SAMPLE, root, ignore=shutil.ignore_patterns("session.json", "truth.json", "calibration.json",
                                                                "calibration_check", "background"))
    assert main(["init", str(root), "--step", "10"]) == 0
    out = capsys.readouterr().out
    assert "0 background frames" in out and "keyed against the colour of the image border" in out
    s = load_session(root)
    assert s.backdrop == {"color": "border", "shadows": True} and s.background_images == ()
    assert main(["init", str(root), "--step", "10", "--backdrop", "20,60,200", "--force"]) == 0
    assert load_session(root).backdrop["color"] == (20.0, 60.0, 200.0)
    assert main(["init", str(root), "--step", "10", "--backdrop", "blue", "--force"]) == 2
    _one_line_error(capsys, "--backdrop", "R,G,B")
    # 'frames' without frames: refused by the session check, nothing left written
    (root / "session.json").unlink()
    assert main(["init", str(root), "--step", "10", "--backdrop", "frames"]) == 2
    _one_line_error(capsys, "backdrop")
    assert not (root / "session.json").exists()


# ------------------------------------------------------------------ moved board, dropped images
MOVED = ["140.png", "160.png", "180.png"]


def _moved_board_copy(dest, shift=(6, 3)):
    """The sample with 3 of its 10 turntable board images shifted (the board moved between stops)
    and one intrinsic image without a board."""
    import cv2

    shutil.copytree(SAMPLE, dest, ignore=shutil.ignore_patterns("calibration.json", "calibration_check"))
    for name in MOVED:
        p = dest / "calibration" / "turntable" / name
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
        cv2.imwrite(str(p), cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), borderMode=cv2.BORDER_REPLICATE))
    blank = dest / "calibration" / "intrinsics" / "03.png"
    cv2.imwrite(str(blank), np.full_like(cv2.imread(str(blank), cv2.IMREAD_UNCHANGED), 128))
    return dest


@pytest.mark.slow
def test_a_moved_board_is_set_aside_and_the_session_still_reconstructs(tmp_path, capsys):
    """Shifting 3 of the 10 turntable board images by (6, 3) px gave a turntable RMS of
    1.79 px and a mesh 22 % too small, exit 0.  Now the 3 are named and set aside
    (measured: 6.70 px each, the others 0.03-0.05 px), the fit's RMS is 0.041 px and the
    mesh within 1 % of the phantom (measured -0.45 %, the intact sample -0.46 %)."""
    root = _moved_board_copy(tmp_path / "moved")
    out = tmp_path / "out"
    assert main(["reconstruct", str(root), "--out", str(out), "--voxel-size", "2", "--quiet", "--strict"]) == 2
    captured = capsys.readouterr()
    report = json.loads((out / "report.json").read_text())
    moved = [f"calibration/turntable/{n}" for n in MOVED]
    assert report["calibration"]["turntable_flagged"] == moved
    assert report["turntable_rms_px"] < 0.1
    assert abs(report["mesh_volume_error_pct"]) < 1.0
    assert len(report["warnings"]) == 1 and all(m in report["warnings"][0] for m in moved)
    assert all(m in captured.err for m in moved)
    # the intrinsic image without a board: listed with the reason, in the report and the terminal
    assert "no 9x6 board found" in report["calibration"]["intrinsic_rejected"]["calibration/intrinsics/03.png"]
    assert "intrinsic image calibration/intrinsics/03.png not used: no 9x6 board found" in captured.out


@pytest.mark.slow
def test_a_turntable_fit_far_above_the_intrinsic_rms_warns(tmp_path, monkeypatch):
    """The same moved boards kept in the fit (flagging disabled): RMS 1.79 px, 80x the
    intrinsic 0.022 px, beyond the stated 5x: a warning."""
    from organlab.calibration import _turntable, calibrate
    from organlab.calibration._result import TURNTABLE_RMS_FACTOR

    monkeypatch.setattr(_turntable, "_threshold", lambda *a, **k: np.inf)
    cal = calibrate(load_session(_moved_board_copy(tmp_path / "moved")))
    assert cal.turntable.flagged == [] and cal.turntable_rms_px > TURNTABLE_RMS_FACTOR * cal.rms_px
    (w,) = cal.warnings()
    assert "turntable fit RMS" in w and f"{TURNTABLE_RMS_FACTOR:g}x" in w


# ------------------------------------------------------------------ calibration.json of the wrong shape
def _wrong(d, case):
    if case == "camera 5":
        return {"camera": 5}
    if case == "K abc":
        d["camera"]["K"] = "abc"
    elif case == "no R_cam":
        del d["turntable"]["R_cam"]
    elif case == "R_cam 1 % off":
        d["turntable"]["R_cam"] = (np.array(d["turntable"]["R_cam"]) * 1.01).tolist()
    return d


@pytest.mark.parametrize(
    "case, key",
    [("camera 5", "camera"), ("K abc", "camera.K"), ("no R_cam", "turntable.R_cam"), ("R_cam 1 % off", "turntable.R_cam")],
)
def test_calibration_json_of_the_wrong_shape_is_one_line(case, key, calibrated, tmp_path, capsys):
    root = tmp_path / "s"
    shutil.copytree(calibrated, root)
    d = json.loads((root / "calibration.json").read_text())
    (root / "calibration.json").write_text(json.dumps(_wrong(d, case)))
    assert main(["reconstruct", str(root), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    _one_line_error(capsys, "calibration.json", key)
    assert not (tmp_path / "o").exists()


def test_a_turntable_rotation_printed_to_few_digits_is_accepted(calibrated, tmp_path):
    from organlab.calibration import Calibration

    d = json.loads((calibrated / "calibration.json").read_text())
    R = np.array(d["turntable"]["R_cam"])
    d["turntable"]["R_cam"] = (R * (1 + 4e-5 * np.array([[1, -1, 0], [0, 1, 1], [1, 0, -1]]))).tolist()  # |R R^T - I| 8e-5
    (tmp_path / "calibration.json").write_text(json.dumps(d))
    cal = Calibration.load(tmp_path / "calibration.json", image_size=(640, 480))
    R2 = cal.turntable.camera.R
    np.testing.assert_allclose(R2 @ R2.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R2, R, atol=1e-4)


# ------------------------------------------------------------------ a scene the limit was not chosen on
@pytest.mark.slow
def test_agreement_on_a_scene_the_limit_never_saw(tmp_path):
    """The grooved specimen, 12 views of 320 x 240, calibrated from its own boards: the
    correct session has no view over the limit (measured: largest disagreement 0.0,
    IoU >= 0.976); the same image for every view puts all 12 over it (measured
    1.1-1.25 %, 3.7x the limit).  (A specimen this close to rotationally symmetric hides a 10 degree
    mislabel from any silhouette test: 0.0 too.)"""
    from organlab.synthetic import make_session

    root = tmp_path / "grooved"
    make_session(root, specimen="grooved", seed=1, image_size=(320, 240), n_views=12, n_intrinsic=8,
                 n_turntable=6, n_background=5, include_camera=False, include_poses=False)
    from organlab.calibration import calibrate

    calibrate(load_session(root)).save(root / "calibration.json")
    rec = reconstruct(root, voxel_size=2.0)
    assert rec.report["warnings"] == []
    assert min(v["agreement"]["iou"] for v in rec.report["views"]) > 0.96

    def same(doc):
        for v in doc["views"]:
            v["image"] = doc["views"][0]["image"]

    bad = reconstruct(_variant(root, tmp_path / "same", same), voxel_size=2.0).report
    assert all(not v["agreement"]["ok"] for v in bad["views"])
    assert "12 of 12 views disagree" in bad["warnings"][0]
