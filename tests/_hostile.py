"""Small sessions for the hostile-input tests (tests/test_hostile*.py), made once per pytest run.

A synthetic 320x240 AAA session with 12 views (organlab.synthetic, seed 7: a scene the defaults
were not tuned on) calibrated from its board images; kept under pytest's base temporary folder so
that every test_hostile module shares it.  Tests copy it before changing anything.
"""

import shutil

from organlab import load_session
from organlab.calibration import calibrate
from organlab.synthetic import make_session


def small_calibrated(tmp_path_factory):
    """Folder of the shared calibrated session (created on first use)."""
    root = tmp_path_factory.getbasetemp() / "hostile_small"
    if not (root / "calibration.json").is_file():
        shutil.rmtree(root, ignore_errors=True)
        make_session(root, seed=7, image_size=(320, 240), n_views=12, n_intrinsic=8, n_turntable=6, n_background=5,
                     include_camera=False, include_poses=False)
        calibrate(load_session(root)).save(root / "calibration.json")
    return root


def copy_session(src, dest):
    shutil.copytree(src, dest, ignore=shutil.ignore_patterns("calibration_check"))
    return dest
