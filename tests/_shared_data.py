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


def made_once(tmp_path_factory, name, make):
    """Folder ``name`` under the pytest run's temporary folder, made by ``make(folder)`` once per run.

    Shared by the run's pytest-xdist workers (the first to ask makes it under a file lock, the others wait
    and read it; as ``tests/_hostile.py`` does for the hostile tests' session).  Read-only for the tests:
    copy it before changing anything.
    """
    import fcntl

    base = tmp_path_factory.getbasetemp()
    top = base.parent if os.environ.get("PYTEST_XDIST_WORKER") and base.name.startswith("popen-") else base
    root, done = top / name, top / f"{name}.done"
    with open(top / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.is_file():
            shutil.rmtree(root, ignore_errors=True)
            make(root)
            done.write_text("made\n")
    return root


def hard_session_24(tmp_path_factory):
    """The phantom in the hard synthetic mode (shadows, +-10 % exposure, 4:2:0 JPEG), 320 x 240, 24 views,
    8 intrinsic and 6 turntable board images, no camera and no poses (self-calibrated), seed 6: a scene
    no default was tuned on.  Made once per run (about 25 s CPU to render) for test_trust.py's correct
    labels and test_backdrop.py's self-calibrated hard session (every other view)."""
    from organlab.synthetic import make_session

    return made_once(tmp_path_factory, "hard24", lambda root: make_session(
        root, hard=True, image_size=(320, 240), n_views=24, n_intrinsic=8, n_turntable=6, n_background=5,
        include_camera=False, include_poses=False, seed=6))


#: test_pipeline.py's posed session: the phantom, 12 views of 320 x 240, true camera and poses given, seed 3
POSED_12 = dict(image_size=(320, 240), n_views=12, n_background=5, views_only=True, seed=3)


def posed_session_12(tmp_path_factory):
    """``make_session(**POSED_12)``, rendered once per run (about 3.5 s CPU) for test_pipeline.py and
    test_robustness.py (which rendered the same settings with seed 7); read-only.  Its truth is its
    ``truth.json`` (``make_session``'s return value but ``session_json``)."""
    from organlab.synthetic import make_session

    return made_once(tmp_path_factory, "posed12", lambda root: make_session(root, **POSED_12))


def sample_calibrated(tmp_path_factory):
    """A copy of the sample (all 36 views) with the ``calibration.json`` its own boards give, computed
    once per run (about 6 s CPU) for test_trust.py's broken copies and test_sweep.py's runs, which need
    a calibration only as set-up; read-only (copy it before writing)."""
    from organlab.calibration import calibrate
    from organlab.session import load_session

    def make(root):
        copy_sample(root)
        calibrate(load_session(root)).save(root / "calibration.json")

    return made_once(tmp_path_factory, "sample_calibrated", make)


#: The pose tests' scene settings (test_poses.py, test_poses_faces.py): 24 views of 320 x 240 px,
#: supersample 2, noise 1 grey level, intrinsics given, turntable calibrated from 8 board images.
POSE_SCENE = dict(image_size=(320, 240), n_views=24, n_intrinsic=0, n_turntable=8, n_background=5, supersample=2,
                  board_supersample=3, noise_sigma=1.0, include_camera=True, include_poses=False)
#: The camera bump after the board images (0.7 degrees, 1.4 mm)
POSE_BUMP = {"rotation_deg": (0.3, 0.6, 0.2), "translation_mm": (1.2, -0.6, 0.4)}


def bumped_session_24(tmp_path_factory):
    """``aaa-7`` (seed 3) under the camera bump ``POSE_BUMP``, ``POSE_SCENE`` settings (24 views), rendered
    once per run for test_poses.py's bumped camera and (every other view: :func:`every_other_view`)
    test_poses_faces.py's viewer; read-only."""
    from organlab.synthetic import make_session

    return made_once(tmp_path_factory, "bump24", lambda root: make_session(
        root, **POSE_SCENE, seed=3, specimen="aaa-7", camera_bump=POSE_BUMP))


def every_other_view(src, dest):
    """A writable copy of the synthetic session ``src`` at ``dest`` with views 0, 2, 4, ... only (in
    ``session.json`` and ``truth.json``, its perturbation's angles too); the image files stay (the unused ones are not read)."""
    shutil.copytree(src, dest)
    for name in ("session.json", "truth.json"):
        doc = json.loads((dest / name).read_text())
        doc["views"] = doc["views"][::2]
        for key in ("commanded_angles_deg", "true_angles_deg"):  # truth.json's perturbation, one per view
            if key in doc.get("perturbation", {}):
                doc["perturbation"][key] = doc["perturbation"][key][::2]
        (dest / name).write_text(json.dumps(doc, indent=2))
    return dest
