"""The public API: the pipeline as a notebook writes it, the typed calibration and its fingerprint,
and sessions that stay untouched."""

import json
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import organlab as ol
from organlab.cli import main
from organlab.errors import CalibrationError
from organlab.surface import read_ply
from tests._shared_data import SAMPLE, copy_sample, sample_calibrated  # noqa: F401 (SAMPLE: for the tests other branches add)

pytestmark = pytest.mark.slow


def _snapshot(root):
    return {p.relative_to(root).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(root.rglob("*"))}


def _read_only(root):
    for p in [root, *root.rglob("*")]:
        mode = p.stat().st_mode
        p.chmod(mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))


def _writable(root):
    for p in [root, *root.rglob("*")]:
        p.chmod(p.stat().st_mode | stat.S_IWUSR)


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    """A read-only copy of the sample session, without calibration.json, and its calibration (set-up for the
    tests that do not compute one themselves: the one computed once per run for test_trust.py and test_sweep.py,
    tests/_shared_data.sample_calibrated, about 6 s CPU saved)."""
    root = tmp_path_factory.mktemp("api") / "aaa"
    copy_sample(root)
    _read_only(root)
    cal = ol.Calibration.load(sample_calibrated(tmp_path_factory) / "calibration.json", image_size=(640, 480))
    yield root, cal
    _writable(root)


def test_snippet_gives_the_mesh_of_organlab_reconstruct(sample, tmp_path):
    """The README's snippet, on a read-only session with no calibration.json, against the CLI's mesh."""
    root, _ = sample
    before = _snapshot(root)
    s = ol.load_session(root)
    cal = ol.calibrate(s)
    sils = ol.silhouettes(s, threshold=None)
    grid = ol.VoxelGrid.from_session(s, voxel_size=2.0)
    field = ol.hull_field(sils, cal.cameras(s), grid, sparse=True)
    raw = ol.mesh_from_field(field, grid)
    mesh, _ = ol.finish_surface(raw, voxel_size=2.0)
    m = ol.measure(mesh)

    out = tmp_path / "out"
    assert main(["reconstruct", str(root), "--out", str(out), "--voxel-size", "2", "--quiet"]) == 0
    assert _snapshot(root) == before  # nothing written into the session
    report = json.loads((out / "report.json").read_text())
    cli_mesh = read_ply(out / "mesh.ply")
    # PLY stores float32 (~1e-5 mm at 200 mm); the two calibrations may differ in their last bits (OpenCV's
    # threads: raw vertices 4e-6 mm apart), which the finished surface's adaptive remeshing carries to a few
    # vertices by up to 1.5e-4 mm (measured: 3 of 8 196 coordinates), same faces
    np.testing.assert_allclose(cli_mesh.vertices, mesh.vertices, atol=1e-3)
    np.testing.assert_array_equal(cli_mesh.faces, mesh.faces)
    assert report["mesh_volume_mm3"] == pytest.approx(m.volume_mm3, rel=1e-6)
    assert report["raw_mesh_volume_mm3"] == pytest.approx(raw.volume, rel=1e-9)
    # the dense field meshes to the same raw surface (its vertices in another order)
    dense = ol.mesh_from_field(ol.hull_field(sils, cal.cameras(s), grid), grid)
    assert len(dense.faces) == len(raw.faces) and dense.volume == pytest.approx(raw.volume, rel=1e-8)
    assert m.watertight and report["watertight"]
    # within the sample's 2 mm accuracy (measured -0.61 %): the snippet is the real pipeline
    assert abs(m.volume_mm3 / s.reference["volume_mm3"] - 1) < 0.01
    # the calibration went to the output folder, and reads back as the same cameras
    back = ol.Calibration.load(out / "calibration.json")
    for a, b in zip(back.cameras(s), cal.cameras(s)):
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, atol=1e-9)


def test_stage_functions_take_what_the_previous_stage_returns(sample):
    root, cal = sample
    s = ol.load_session(root)
    sils = ol.silhouettes(s)
    grid = ol.VoxelGrid.from_session(s, voxel_size=4.0)
    cams = cal.cameras(s)
    from_objects = ol.carve(sils, cams, grid)
    from_arrays = ol.carve([x.mask for x in sils], cams, grid)
    np.testing.assert_array_equal(from_objects, from_arrays)
    np.testing.assert_array_equal(ol.hull_field(sils, cams, grid), ol.hull_field([x.coverage for x in sils], cams, grid))
    assert len(s.images()) == len(s.views) and s.images()[0].shape == (480, 640, 3)


def test_changed_square_size_is_not_reused_silently(sample, tmp_path, capsys):
    """A calibration.json computed with 20 mm squares, in a session whose pattern now says 25 mm."""
    root, cal = sample
    changed = tmp_path / "sq25"
    shutil.copytree(root, changed)
    _writable(changed)
    raw = json.loads((changed / "session.json").read_text())
    raw["pattern"]["square_size"] = 25.0
    (changed / "session.json").write_text(json.dumps(raw))
    cal.save(changed / "calibration.json")

    s = ol.load_session(changed)
    why = ol.Calibration.load(changed / "calibration.json").mismatch(s)
    assert len(why) == 1 and "pattern 9x6 of 20 mm differs from the session's 9x6 of 25 mm" in why[0]
    # given explicitly: refused, one line, exit 2
    code = main(["reconstruct", str(changed), "--out", str(tmp_path / "o1"), "--voxel-size", "4", "--quiet",
                 "--calibration", str(changed / "calibration.json")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "does not belong to this session" in err and "25 mm" in err
    # the session's own: recalibrated, and the report and summary say why
    code = main(["reconstruct", str(changed), "--out", str(tmp_path / "o2"), "--voxel-size", "4", "--quiet"])
    out = capsys.readouterr().out
    assert code == 0 and "recomputed: calibration.json not used" in out
    report = json.loads((tmp_path / "o2" / "report.json").read_text())
    assert report["calibration"]["source"].startswith("recomputed") and "calibration" in report["timings_s"]
    # 25 mm squares scale the world by 1.25: the new calibration's camera is 1.25x as far from the axis
    new = ol.Calibration.load(tmp_path / "o2" / "calibration.json")
    np.testing.assert_allclose(new.turntable.camera.t, 1.25 * cal.turntable.camera.t, rtol=1e-6)


def test_calibration_of_another_session_is_detected(sample, tmp_path):
    """Same rig, other board images: the fingerprint tells them apart; another image size too."""
    root, cal = sample
    other = tmp_path / "other"
    shutil.copytree(root, other)
    _writable(other)
    raw = json.loads((other / "session.json").read_text())
    tt = raw["calibration"]["turntable_images"]
    tt[0], tt[1] = {**tt[0], "image": tt[1]["image"]}, {**tt[1], "image": tt[0]["image"]}  # two images swapped
    (other / "session.json").write_text(json.dumps(raw))
    why = cal.mismatch(ol.load_session(other))
    assert why == ["it was computed from other board images (or angles) than the session's"]
    with pytest.raises(CalibrationError, match="does not belong to this session: it was computed from other board images"):
        ol.calibration_for(other, calibration=cal)
    assert cal.mismatch(ol.load_session(root)) == []

    small = ol.Calibration(cal.camera.__class__(cal.camera.K / 2 + np.diag([0, 0, 0.5]), cal.camera.dist,
                                                image_size=(320, 240)), fingerprint=cal.fingerprint)
    s = ol.load_session(root)
    assert small.mismatch(s)[0] == "it is for 320x240 images, the session's are 640x480"
    with pytest.raises(CalibrationError, match="calibration is for 320x240 images, the session's are 640x480"):
        small.cameras(s)


@pytest.mark.parametrize(
    "content, message",
    [
        ('{"camera": 5}', r"camera: must be an object with K, dist, image_size, got 5"),
        ('{"camera": {"K": "abc", "dist": [0, 0, 0, 0, 0], "image_size": [640, 480]}}', r"camera\.K: must be a 3x3 matrix"),
        ('{"camera": {"K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]], "image_size": [640, 480]}, "turntable": {"t_cam": [0, 0, 500]}}',
         r"turntable\.R_cam: is missing"),
        ('{"camera": {"K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]], "dist": [0, 0], "image_size": [640, 480]}}',
         r"camera\.dist: must be 5 numbers"),
        ("[1, 2]", r"must be a JSON object"),
        ("{oops", r"invalid JSON"),
    ],
)
def test_bad_calibration_file_is_one_clear_line_per_problem(tmp_path, content, message):
    path = tmp_path / "calibration.json"
    path.write_text(content)
    with pytest.raises(CalibrationError, match=message) as e:
        ol.Calibration.load(path)
    assert str(path) in str(e.value)


def test_calibrate_cli_writes_to_out_or_in_place(sample, tmp_path):
    root, _ = sample
    copy = tmp_path / "s"
    shutil.copytree(root, copy)
    _writable(copy)
    before = _snapshot(copy)
    assert main(["calibrate", str(copy), "--out", str(tmp_path / "cal"), "--quiet"]) == 0
    assert _snapshot(copy) == before
    assert (tmp_path / "cal" / "calibration.json").is_file()
    assert len(list((tmp_path / "cal" / "calibration_check").glob("*.png"))) == 25
    assert main(["calibrate", str(copy), "--in-place", "--quiet"]) == 0
    assert (copy / "calibration.json").is_file() and (copy / "calibration_check").is_dir()
    rec = ol.reconstruct(copy, voxel_size=4.0)
    assert rec.report["calibration"]["source"] == "reused, verified"


def test_import_organlab_stays_light():
    """The top-level names load their modules on first use: no numba, scipy, cv2 at import."""
    code = ("import sys, organlab; heavy = [m for m in ('numba', 'scipy', 'cv2', 'skimage', 'pyvista') if m in sys.modules];"
            "print(heavy); organlab.hull_field; print('numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}).stdout.split()
    assert out == ["[]", "True"]
