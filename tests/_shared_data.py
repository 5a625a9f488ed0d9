"""Where the optional real data of ../shared lies, for the tests that use it (they skip, naming the path, without it).

``../shared/data`` beside the repository; ``ORGANLAB_SHARED_DATA`` overrides it (e.g. from a git worktree).
"""

import os
from pathlib import Path

import pytest

import organlab

SHARED_DATA = Path(os.environ.get("ORGANLAB_SHARED_DATA", Path(organlab.__file__).resolve().parents[2] / "shared" / "data"))
DINO = SHARED_DATA / "dinoSparseRing"
#: Why the dinoSparseRing tests skip: where they looked, and how to point them elsewhere
DINO_MISSING = f"dinoSparseRing not found at {DINO} (set ORGANLAB_SHARED_DATA to the folder that holds dinoSparseRing/)"
needs_dino = pytest.mark.skipif(not (DINO / "dinoSR_par.txt").is_file(), reason=DINO_MISSING)
