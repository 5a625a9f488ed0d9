"""Fixtures shared by the test files: the bundled sample session and small sessions made from it.

``SAMPLE`` (the path) and ``copy_sample`` live in ``_shared_data`` so that a test file can also use
them at import time or in its own fixtures (``from tests._shared_data import SAMPLE, copy_sample``).
"""

import pytest
from tests._shared_data import SAMPLE, copy_sample

from organlab.session import load_session
from organlab.synthetic import with_true_cameras


@pytest.fixture(scope="session")
def sample_dir():
    """The bundled sample session's folder (read-only: copy it with ``sample_copy`` to write)."""
    return SAMPLE


@pytest.fixture(scope="session")
def sample_session():
    """The bundled sample, loaded (:class:`organlab.session.Session`)."""
    return load_session(SAMPLE)


@pytest.fixture
def sample_copy(tmp_path):
    """Factory: ``sample_copy(name="sample", calibration=False, views=None)`` -> Path of a fresh
    writable copy of the sample under this test's ``tmp_path`` (see ``_shared_data.copy_sample``)."""

    def make(name="sample", **kw):
        return copy_sample(tmp_path / name, **kw)

    return make


@pytest.fixture(scope="session")
def true_sample(tmp_path_factory):
    """The sample with its true cameras (the poses that rendered it), made once per run; read-only."""
    return with_true_cameras(SAMPLE, tmp_path_factory.mktemp("true_sample") / "aaa")


@pytest.fixture(scope="session")
def small_session(tmp_path_factory):
    """A small session: the sample with its calibration and every 6th view (6 views, 60 degrees
    apart), for tests that need a whole reconstruction quickly; read-only."""
    return load_session(copy_sample(tmp_path_factory.mktemp("small") / "aaa6", calibration=True, views=6))


def pytest_configure(config):
    """One folder of board detections for the whole run (``ORGANLAB_DETECTION_CACHE``,
    organlab/calibration/_board.py): the xdist workers, notebook kernels and command-line subprocesses
    started from here inherit it, so each board image is measured once per run instead of once per process
    (the sample's 25 boards: about 4.5 s CPU in each fresh process that calibrates it).  Made by the process
    that starts the run (the workers find it set) and removed at its end; a folder already named in the
    environment is used as it is and kept."""
    import os
    import tempfile

    from organlab.calibration._board import DETECTION_CACHE_ENV
    from organlab.synthetic._simrig import SPEEDUP_ENV

    # the simulated table's moves 10x faster again (organlab/synthetic/_simrig.py): they are real-time waits that
    # no test measures (every capture test, its notebook and its command-line subprocesses wait for them); a value
    # already in the environment is kept (ORGANLAB_SIM_SPEEDUP=1: the moves' own time_scale alone)
    os.environ.setdefault(SPEEDUP_ENV, "10")
    if not os.environ.get(DETECTION_CACHE_ENV):
        folder = tempfile.mkdtemp(prefix="organlab-detections-")
        os.environ[DETECTION_CACHE_ENV] = folder
        config._organlab_detections = folder


def pytest_unconfigure(config):
    import os
    import shutil

    folder = getattr(config, "_organlab_detections", None)
    if folder:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop("ORGANLAB_DETECTION_CACHE", None)


# Under pytest-xdist (`make test`: --dist loadfile --no-loadscope-reorder) the work is handed to the workers
# in collection order, one unit at a time as each worker runs low: the longest first, so that no long unit
# starts last while the other worker idles (xdist's own order is by number of tests, which put test_photo,
# test_benchmarks and the JupyterLab test, 20-85 s each with 1-7 tests, at the end).  A unit is a test file
# (its module fixtures are made once), except the tests named in UNIT_SECONDS: each is a unit of its own
# (they share no module fixture with the rest of their file), so that test_notebooks' twelve notebook runs
# (about 240 s together) spread over both workers instead of holding one.
# FILE_SECONDS: CPU seconds (user + sys, children included: kernels, subprocesses, JupyterLab, the Dask workers) of a
# file alone, its module fixtures included, less its tests that are units of their own.  Re-measured per test (a
# pytest plugin summing getrusage of the process and its children over each test's set-up, call and tear-down) by
# issue 24's helper `suite` on 2026-12-03 (second pass), one process per file, numba cache warm, under a load of 12-20
# on 2 cores: test_trust, test_sweep, test_api, test_examples, test_pipeline, test_capture, test_coloring,
# test_benchmarks, test_notebook_jupyterlab (16 s in the browser, 21 s of server and kernel reaped at tear-down),
# test_hostile_kill, test_backdrop, test_calibration, test_calibration_real and the notebooks (test_trust: 103 s;
# 133 s the first time in a fresh worktree, numba compiling).  test_sweep counts its Dask workers (34 s at the cluster's
# tear-down; 14 s of its serial reference and as much in a worker are the pose fit at threshold 35, refused). test_api
# counts the run's shared sample calibration (6 s) that test_trust or test_sweep usually makes first.
# test_coloring_robust: 50 s without the dinoSparseRing tests (they skip without ../shared/data), 70 s with them
# (first pass).  The rest from the first pass (one process, load 13-21: the dino photo test 59 s, the rest of
# test_photo 28 s; test_hostile_results 7 s once the hostile tests' shared session is made, 12 s, by whichever comes
# first; test_poses_faces 14 s once test_poses has made the bumped render they share; test_agreement_limits 4 s CPU,
# 25 s idle: its simulated capture waits).  The files not named follow, most tests first.  Refresh them when they move
# (`pytest --durations=0`, or CPU per test).  Since the run-wide board detections (pytest_configure above; third
# pass, 2026-12-03 evening) the processes that calibrate the sample after the first skip its 25 detections (about
# 4.5 CPU s each): test_examples (02, 04, 05, 06: 41 s in a whole run under load 15 -> 32 s alone under load 9, the
# first detection included), notebooks 01 (11.3 -> 5.7-6.1 s), 03 and 05 (about 4 and 2.5 s less), test_hostile_kill
# (the mesh reference made once, the calibrate reruns' detections read back: 59 s in that run -> 44 s alone under
# load 14); their figures below are the old ones scaled by these.  Fourth pass (2026-12-04, CPU per test as above, one
# process per file, load 6-11): test_trust 103 -> 51 (the pose check's speed-up), test_poses 57 -> 29 (35 with its
# dinoSparseRing test), test_real_dino 31, test_photo 25 without its dino unit, test_coloring_robust 52 (its dino
# backdrop session moved to test_real_dino); test_sweep measured 80 CPU s but stays first (its cluster's start, the
# workers' imports and its `organlab sweep` subprocess make its wall far longer than its CPU).  test_real_dino
# 32.1 -> 24.1 (user + sys, one process, load ~10, 2026-12-04: the joint silhouette step's same masks for less CPU
# and the bbox hull by carve instead of carve_reference).
FILE_SECONDS = {
    "test_sweep.py": 120, "test_trust.py": 51, "test_coloring_robust.py": 52, "test_hostile_kill.py": 52,
    "test_poses.py": 35, "test_examples.py": 38, "test_api.py": 51, "test_pipeline.py": 39, "test_coloring.py": 39,
    "test_notebook_jupyterlab.py": 39, "test_backdrop.py": 47, "test_capture.py": 34, "test_real_dino.py": 24,
    "test_photo.py": 25, "test_calibration.py": 28, "test_agreement_limits.py": 25, "test_band.py": 24,
    "test_benchmarks.py": 23, "test_joint_silhouettes.py": 21, "test_calibration_real.py": 30,
    "test_finish_deviation.py": 18, "test_hostile_calibration.py": 17, "test_sample_session.py": 17,
    "test_hostile_results.py": 15, "test_surface_aaa.py": 15, "test_hostile_fuzz.py": 14,
    "test_hostile_outputs.py": 14, "test_field.py": 14, "test_poses_faces.py": 14, "test_camera_formats.py": 11,
    "test_notebooks.py": 3,
    # fourth pass (2026-12-04, one process, load 6-11): the files the table did not name, which queued last by test
    # count although some are long (test_poses_drift, 4 tests, and test_viewer_browser, 5 tests of a real browser whose
    # wall is several times its CPU, were among the last units handed out)
    "test_viewer.py": 48, "test_viewer_browser.py": 30, "test_widgets.py": 26, "test_poses_drift.py": 20,
    "test_synthetic.py": 17, "test_mutants.py": 12, "test_carving.py": 9, "test_hostile_checks.py": 9,
    "test_poses_check.py": 8, "test_voxels_npz.py": 8, "test_docs_examples.py": 6, "test_robustness.py": 5,
    "test_engine.py": 5, "test_hostile_access.py": 5, "test_capture_view.py": 5, "test_agreement_faces.py": 4,
}
#: Tests scheduled as units of their own (node id from the file's name on; or up to a "[": each of its
#: parametrizations) -> CPU seconds of one.  The notebooks: each runs in its own kernel (measured CPU, kernel
#: included, under load 14, 2026-12-03, second pass; 04's solutions 41 s the first time the colouring kernels
#: loaded in the run, 28 s after); the dino photo test shares nothing with test_photo's bowls.
_NB = "test_notebooks.py::test_notebook_executes"
UNIT_SECONDS = {
    f"{_NB}[04_voxel_coloring-solutions]": 28, f"{_NB}[04_voxel_coloring-student]": 27,
    f"{_NB}[03_voxel_carving-solutions]": 23, f"{_NB}[03_voxel_carving-student]": 20,
    f"{_NB}[02_background_and_silhouettes-solutions]": 19, f"{_NB}[02_background_and_silhouettes-student]": 13,
    f"{_NB}[05_surface_repair_and_measures-solutions]": 15, f"{_NB}[05_surface_repair_and_measures-student]": 12,
    f"{_NB}[06_live_capture-solutions]": 16, f"{_NB}[06_live_capture-student]": 11,
    f"{_NB}[01_calibration-solutions]": 8, f"{_NB}[01_calibration-student]": 8,
    _NB: 15,  # a notebook added later
    "test_notebooks.py::test_calibration_exercise_survives_a_click_between_cells": 7,
    "test_photo.py::test_dino_photo_keeps_the_silhouettes": 8,  # 60 at full size and 3 mm (issue 24, 2026-12-04)
}


def _unit(nodeid):
    """The scheduling unit of a test: (unit, its CPU seconds), the file's path and None for most tests."""
    path, _, rest = nodeid.partition("::")
    rel = path.rsplit("/", 1)[-1] + "::" + rest
    for key in (rel, rel.split("[", 1)[0]):
        if key in UNIT_SECONDS:
            return nodeid, UNIT_SECONDS[key]
    return path, None


@pytest.hookimpl(tryfirst=True, optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """--dist loadfile with the units above: a file, or one of UNIT_SECONDS' tests alone (first: xdist's own
    hook would otherwise answer)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class _Units(LoadFileScheduling):
        def _split_scope(self, nodeid):
            return _unit(nodeid)[0]

    return _Units(config, log)


def pytest_collection_modifyitems(session, config, items):
    import os

    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return  # one process: the files in their usual order
    count = {}
    for it in items:
        count[it.path.name] = count.get(it.path.name, 0) + 1

    def cost(it):
        unit, seconds = _unit(it.nodeid)
        if seconds is None:
            seconds = FILE_SECONDS.get(it.path.name, 0)
        return (-seconds, -count[it.path.name], unit)

    items.sort(key=cost)  # stable: each unit's tests keep their order
