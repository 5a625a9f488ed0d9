"""Issue 26, item 1: a calibration.json is reused only when its numbers reproduce its own RMS.

The fingerprint covers what a calibration was computed from, never the fitted values: a file
whose fx and fy were raised by 8 % (fingerprint untouched) was reused silently and shrank the
mesh by 20.9 %.  Here the stored corners are reprojected with the stored camera and poses.
"""

import json
import re

import numpy as np
import pytest
from _hostile import copy_session, small_calibrated

from organlab import load_session
from organlab.calibration import Calibration, calibration_for
from organlab.camera import Camera
from organlab.errors import CalibrationError, OrganlabError


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return small_calibrated(tmp_path_factory)


def _edit_calibration(root, edit):
    p = root / "calibration.json"
    d = json.loads(p.read_text())
    edit(d)
    p.write_text(json.dumps(d))
    return p


def _found_px(text):
    return float(re.search(r"an RMS of ([0-9.e+-]+) px", text).group(1))


def _scale_focal(d, f=1.08):
    d["camera"]["K"][0][0] *= f
    d["camera"]["K"][1][1] *= f


def test_untouched_calibration_is_reused_verified(small):
    cal, how = calibration_for(load_session(small))
    assert how == "reused, verified"
    assert cal.verify(load_session(small)) == []


def test_tampered_focal_length_is_recomputed_not_reused(small, tmp_path):
    root = copy_session(small, tmp_path / "s")
    good = Calibration.load(small).camera.K
    _edit_calibration(root, _scale_focal)
    cal, how = calibration_for(load_session(root))
    assert how.startswith("recomputed") and "reprojected" in how, how
    assert _found_px(how) > 1.0  # 6.39 px on the seed-0 session, against 0.034 stored
    # the recomputed camera is the untampered fit again (same images, same detector)
    assert np.allclose(cal.camera.K, good, rtol=1e-6)


@pytest.mark.parametrize("factor", [1.01, 0.999])
def test_small_tampering_is_seen(small, tmp_path, factor):
    """+1 % gives a reprojection RMS of 0.80 px against 0.034 stored; -0.1 % about 0.08 px."""
    root = copy_session(small, tmp_path / "s")
    _edit_calibration(root, lambda d: _scale_focal(d, factor))
    cal = Calibration.load(root)
    why = cal.verify(load_session(root))
    stored = Calibration.load(small).rms_px
    assert why and f"not the {stored:.3g} px" in why[0] and _found_px(why[0]) > 2 * stored, why


def test_tampered_calibration_without_board_images_is_refused(small, tmp_path, capsys):
    root = copy_session(small, tmp_path / "s")
    _edit_calibration(root, _scale_focal)
    doc = json.loads((root / "session.json").read_text())
    del doc["calibration"]  # nothing to recalibrate from
    (root / "session.json").write_text(json.dumps(doc))
    with pytest.raises(CalibrationError) as e:
        calibration_for(load_session(root))
    assert "\n" not in str(e.value) and "reprojected" in str(e.value)


def test_given_tampered_calibration_is_refused(small, tmp_path):
    bad = tmp_path / "cal.json"
    d = json.loads((small / "calibration.json").read_text())
    _scale_focal(d)
    bad.write_text(json.dumps(d))
    with pytest.raises(CalibrationError, match="cannot be trusted"):
        calibration_for(load_session(small), calibration=bad)
    _, how = calibration_for(load_session(small), calibration=small / "calibration.json")
    assert how == "given, verified"


def test_moved_principal_point_and_turntable_pose_are_seen(small, tmp_path):
    root = copy_session(small, tmp_path / "s")
    _edit_calibration(root, lambda d: d["turntable"]["t_cam"].__setitem__(2, d["turntable"]["t_cam"][2] * 1.05))
    why = Calibration.load(root).verify(load_session(root))
    assert len(why) == 1 and "turntable" in why[0], why
    _edit_calibration(root, lambda d: d["camera"]["K"][0].__setitem__(2, 1e5))
    why = Calibration.load(root).verify(load_session(root))
    assert "principal point" in why[0], why


def test_calibration_without_corners_is_not_silently_trusted(small, tmp_path):
    root = copy_session(small, tmp_path / "s")

    def strip(d):
        for part in (d["camera"], d["turntable"]):
            for e in part["images"].values():
                e.pop("corners_px", None)

    _edit_calibration(root, strip)
    _, how = calibration_for(load_session(root))
    assert how.startswith("recomputed") and "cannot be checked" in how, how


# ------------------------------------------------------------- malformed numbers: one line each
def _nested(n):
    return json.loads("[" * n + "]" * n) if n < 500 else None


@pytest.mark.parametrize("edit, needle", [
    (lambda d: d["camera"].__setitem__("std", {"fc": "wide"}), "camera.std.fc"),
    (lambda d: d["camera"].__setitem__("std", [1, 2]), "camera.std"),
    (lambda d: d["camera"].__setitem__("rejected", 5), "camera.rejected"),
    (lambda d: d["camera"].__setitem__("rms_px", "low"), "camera.rms_px"),
    (lambda d: d["camera"].__setitem__("rms_px", "__BIG__"), "camera.rms_px"),
    (lambda d: d["turntable"].__setitem__("rms_px", -1), "turntable.rms_px"),
    (lambda d: d["pattern"].__setitem__("square_size", "20"), "pattern"),
    (lambda d: d["pattern"].__setitem__("square_size", "__BIG__"), "pattern"),
    (lambda d: d["camera"].__setitem__("image_size", 320), "camera.image_size"),
    (lambda d: d["turntable"].__setitem__("axis", [1]), "turntable.axis"),
    (lambda d: next(iter(d["camera"]["images"].values())).__setitem__("rvec", [1, "a", 3]), "rvec"),
    (lambda d: next(iter(d["camera"]["images"].values())).__setitem__("corners_px", [[1, 2, 3]]), "corners_px"),
    (lambda d: next(iter(d["turntable"]["images"].values())).__setitem__("angle_deg", [0]), "angle_deg"),
])
def test_mistyped_fields_give_one_line(small, tmp_path, edit, needle):
    root = tmp_path / "c"
    root.mkdir()
    d = json.loads((small / "calibration.json").read_text())
    edit(d)
    # 1e400 parses as an infinite float (strict JSON, not refused by the parser)
    (root / "calibration.json").write_text(json.dumps(d).replace('"__BIG__"', "1e400"))
    with pytest.raises(CalibrationError) as e:
        Calibration.load(root)
    msg = str(e.value)
    assert "\n" not in msg and needle in msg and str(root) in msg, msg


@pytest.mark.parametrize("text, needle", [
    ("[" * 100000 + "]" * 100000, "nested 100000 deep"),
    ('{"camera": {"K": NaN}}', "NaN is not JSON"),
    ('{"camera": {"K": Infinity}}', "Infinity is not JSON"),
    (b"\xff\xfe{}", "UTF-8"),
])
def test_unparseable_calibration_gives_one_line(tmp_path, text, needle):
    p = tmp_path / "calibration.json"
    p.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(OrganlabError) as e:
        Calibration.load(p)
    assert "\n" not in str(e.value) and needle in str(e.value), str(e.value)


@pytest.mark.parametrize("field", ["K", "dist", "R", "t"])
def test_camera_rejects_non_finite_values(field):
    kw = {"K": np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]]), "dist": np.zeros(5), "R": np.eye(3), "t": np.zeros(3)}
    kw[field] = np.array(kw[field], dtype=float)
    kw[field].flat[0] = np.nan
    with pytest.raises(ValueError, match=f"{field} must hold finite numbers"):
        Camera(kw["K"], kw["dist"], kw["R"], kw["t"], image_size=(100, 80))
