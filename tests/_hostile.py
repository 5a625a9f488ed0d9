"""Small sessions for the hostile-input tests (tests/test_hostile*.py), made once per pytest run.

A synthetic 320x240 AAA session with 12 views (organlab.synthetic, seed 7: a scene the defaults
were not tuned on) calibrated from its board images; kept under the run's temporary folder so
that every test_hostile module shares it, on every pytest-xdist worker (the first makes it under
a lock, about 12 s of CPU; the others wait for it and read it).  Tests copy it before changing anything.
"""

import fcntl
import os
import shutil

from organlab import load_session
from organlab.calibration import calibrate
from organlab.synthetic import make_session


def run_temp(tmp_path_factory):
    """The pytest run's temporary folder, shared by its xdist workers (each has its own ``popen-gwN`` in it)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") and base.name.startswith("popen-") else base


def small_calibrated(tmp_path_factory):
    """Folder of the shared calibrated session (created on first use, once per run)."""
    top = run_temp(tmp_path_factory)
    root = top / "hostile_small"
    with open(top / "hostile_small.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one worker makes it; calibration.json, written last, marks it done
        if not (root / "calibration.json").is_file():
            shutil.rmtree(root, ignore_errors=True)
            make_session(root, seed=7, image_size=(320, 240), n_views=12, n_intrinsic=8, n_turntable=6,
                         n_background=5, include_camera=False, include_poses=False)
            calibrate(load_session(root)).save(root / "calibration.json")
    return root


def copy_session(src, dest):
    shutil.copytree(src, dest, ignore=shutil.ignore_patterns("calibration_check"))
    return dest
