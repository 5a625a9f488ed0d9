"""Where the optional real data of ../shared lies, for the tests that use it (they skip, naming the path, without it).

``../shared/data`` beside the repository; ``ORGANLAB_SHARED_DATA`` overrides it (e.g. from a git worktree).
"""

import json
import os
import shutil
from pathlib import Path

import pytest

import organlab

SHARED_DATA = Path(os.environ.get("ORGANLAB_SHARED_DATA", Path(organlab.__file__).resolve().parents[2] / "shared" / "data"))
DINO = SHARED_DATA / "dinoSparseRing"
#: Why the dinoSparseRing tests skip: where they looked, and how to point them elsewhere
DINO_MISSING = f"dinoSparseRing not found at {DINO} (set ORGANLAB_SHARED_DATA to the folder that holds dinoSparseRing/)"
needs_dino = pytest.mark.skipif(not (DINO / "dinoSR_par.txt").is_file(), reason=DINO_MISSING)

#: The repository, and the bundled sample session (a synthetic AAA phantom, 36 views; read it, never write into it).
ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_sessions" / "aaa_phantom"


def copy_sample(root, *, calibration=False, views=None):
    """A writable copy of the sample at ``root``: without its calibration (``calibration.json``,
    ``calibration_check/``) unless ``calibration``; only every ``views``-th view when given."""
    ignore = None if calibration else shutil.ignore_patterns("calibration.json", "calibration_check")
    shutil.copytree(SAMPLE, root, ignore=ignore)
    if views:
        doc = json.loads((root / "session.json").read_text())
        doc["views"] = doc["views"][::views]
        (root / "session.json").write_text(json.dumps(doc, indent=2))
    return root
