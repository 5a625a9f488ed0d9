"""Issue 26, item 6: a capture resumes only with the drive and camera it began with.

Resuming with gear ratio 72 on a session captured at 90:1 was accepted and the angle audit then
blamed lost steps; a camera file with NaN in K was accepted.
"""

import json

import numpy as np
import pytest

from organlab.camera import Camera
from organlab.capture import CaptureError, StallError, capture_session
from organlab.synthetic import SimRig
from organlab.capture._run import read_intrinsics


def _capture(root, rig, *, gear_ratio=90.0, intrinsics=None, **kw):
    opts = dict(step_deg=60.0, n_background=1, intrinsics=intrinsics or rig.camera_model, prompt=rig.prompt,
                say=lambda s: None)
    opts.update(kw)
    with rig.turntable(gear_ratio=gear_ratio, timeout=0.2, poll_interval=0.005) as t:
        return capture_session(root, t, rig.camera(), **opts)


@pytest.fixture
def stopped(tmp_path):
    """A capture that stalled after its board images and 2 views."""
    root = tmp_path / "s"
    with SimRig(time_scale=20.0, image_size=(320, 240)) as rig:
        rig.controller.inject("stall", on="MA", after=8)
        with pytest.raises(StallError):
            _capture(root, rig)
    return root


def _listed(root):
    doc = json.loads((root / "session.json").read_text())
    return doc["views"], doc["calibration"]["turntable_images"]


def test_resume_with_another_gear_ratio_is_refused_naming_both(stopped):
    before = _listed(stopped)
    with SimRig(time_scale=20.0, image_size=(320, 240)) as rig, pytest.raises(CaptureError) as e:
        _capture(stopped, rig, gear_ratio=72.0)
    msg = str(e.value)
    # 200 full steps x 256 microsteps x 90 / 360 = 12800 per degree; at 72:1, 10240
    assert "12800" in msg and "10240" in msg and "\n" not in msg, msg
    assert _listed(stopped) == before  # nothing taken, nothing lost
    with SimRig(time_scale=20.0, image_size=(320, 240)) as rig:  # the same settings complete it
        _capture(stopped, rig)
    assert len(_listed(stopped)[0]) == 6


def test_resume_with_other_intrinsics_is_refused_naming_both(stopped):
    with SimRig(time_scale=20.0, image_size=(320, 240)) as rig:
        K = np.array(rig.camera_model.K)
        K[0, 0] *= 1.1
        other = Camera(K, rig.camera_model.dist, image_size=rig.camera_model.image_size)
        with pytest.raises(CaptureError) as e:
            _capture(stopped, rig, intrinsics=other)
    msg = str(e.value)
    assert "intrinsics" in msg and f"fx {K[0, 0]:g}" in msg and str(round(rig.camera_model.K[0, 0], 1))[:4] in msg, msg


def test_camera_file_with_nan_is_refused(tmp_path):
    p = tmp_path / "calibration.json"
    p.write_text('{"camera": {"K": [[NaN, 0, 160], [0, 400, 120], [0, 0, 1]], "dist": [0, 0, 0, 0, 0], '
                 '"image_size": [320, 240]}}')
    with pytest.raises(CaptureError) as e:
        read_intrinsics(p)
    assert "NaN is not JSON" in str(e.value) and "\n" not in str(e.value)
    p.write_text('{"camera": {"K": [[1e400, 0, 160], [0, 400, 120], [0, 0, 1]], "dist": [0, 0, 0, 0, 0]}}')  # inf
    with pytest.raises(CaptureError, match="finite"):
        read_intrinsics(p)


@pytest.mark.parametrize("value", ["abc", "-1", "0", "inf"])
def test_bad_sim_speedup_is_one_line_exit_2(tmp_path, monkeypatch, capsys, value):
    from organlab.cli import main

    monkeypatch.setenv("ORGANLAB_SIM_SPEEDUP", value)
    code = main(["capture", "--out", str(tmp_path / "s"), "--turntable", "sim", "--camera", "sim", "--step", "90"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "ORGANLAB_SIM_SPEEDUP must be a positive number" in err[0] and repr(value) in err[0]
    assert not (tmp_path / "s").exists()  # refused before anything was written
