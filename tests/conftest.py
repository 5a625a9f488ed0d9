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
