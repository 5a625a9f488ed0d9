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


# Under pytest-xdist (`make test`: --dist loadfile --no-loadscope-reorder) the files are handed to the
# workers in collection order, one at a time as each worker runs out: the longest first, so that no
# long file starts last while the other worker idles (xdist's own order is by number of tests, which put
# test_photo, test_benchmarks and the JupyterLab test, 20-85 s each with 1-7 tests, at the end).
# Approximate seconds per file on a quiet 2-core machine (the closing note's slowest tests, summed per
# file), and where issue 24's helper measured it, the file's CPU seconds alone (user + sys, kernels
# included, 2026-12-03 under load: test_notebooks 218, test_photo 123, test_trust 101; test_pipeline and
# test_backdrop about 42 and 28 once their shared sessions are made; test_poses + test_poses_faces 88 in one
# run, about 4/5 of it test_poses, now that they share the bumped render, load 9-16); the files not named
# follow, most tests first.  Refresh from `pytest --durations=0` when they move.
FILE_SECONDS = {
    "test_notebooks.py": 220, "test_photo.py": 120, "test_trust.py": 100, "test_sweep.py": 60,
    "test_hostile_results.py": 45, "test_pipeline.py": 40, "test_coloring_robust.py": 40, "test_coloring.py": 35,
    "test_poses.py": 70, "test_backdrop.py": 30, "test_capture.py": 30, "test_camera_formats.py": 30,
    "test_real_dino.py": 30, "test_poses_faces.py": 20,
    "test_benchmarks.py": 25, "test_notebook_jupyterlab.py": 25, "test_agreement_limits.py": 25,
}


def pytest_collection_modifyitems(session, config, items):
    import os

    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return  # one process: the files in their usual order
    count = {}
    for it in items:
        count[it.path.name] = count.get(it.path.name, 0) + 1
    order = sorted(count, key=lambda f: (-FILE_SECONDS.get(f, 0), -count[f], f))
    rank = {f: k for k, f in enumerate(order)}
    items.sort(key=lambda it: rank[it.path.name])  # stable: each file's tests keep their order
