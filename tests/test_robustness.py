"""Bad silhouettes through the whole pipeline: salt-and-pepper noise, a wrong view."""

import json
import shutil

import cv2
import numpy as np
import pytest

from organlab import load_session
from organlab.pipeline import reconstruct
from tests._shared_data import posed_session_12


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """test_pipeline.py's posed session (12 views of 320 x 240, seed 3; tests/_shared_data.posed_session_12, made
    once per run; read-only: the tests below edit copies).  It was a session of its own with seed 7: the figures
    below were measured on both (seed 7 / seed 3)."""
    root = posed_session_12(tmp_path_factory)
    return root, json.loads((root / "truth.json").read_text()), reconstruct(root, voxel_size=2.0)


def _copy_with(root, dest, edit):
    """Copy a session and rewrite each view image through ``edit(i, rgb) -> rgb``."""
    shutil.copytree(root, dest)
    s = load_session(dest)
    for i, v in enumerate(s.views):
        img = edit(i, s.read(v.image))
        # views are PNG in this session: lossless, so the edit is exactly what is read back
        assert cv2.imwrite(str(v.image), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    return dest


def test_salt_and_pepper_noise_changes_nothing_much(clean, tmp_path):
    root, truth, ref = clean
    rng = np.random.default_rng(0)

    def salt_pepper(i, img):
        out = img.copy()
        hit = rng.random(img.shape[:2]) < 0.02  # 2 % of the pixels
        out[hit] = np.where(rng.random((hit.sum(), 1)) < 0.5, 0, 255)
        return out

    noisy = reconstruct(_copy_with(root, tmp_path / "noisy", salt_pepper), voxel_size=2.0)
    # no tunnel, no spurious blobs: the volume moves by well under 1 % (measured +0.70 % / +0.70 %, 0.071 % / 0.070 %
    # of the voxels changed)
    assert noisy.mesh.volume == pytest.approx(ref.mesh.volume, rel=0.01)
    assert noisy.mesh.is_watertight
    assert np.mean(noisy.occupancy != ref.occupancy) < 0.002


def test_tolerance_survives_a_wrong_view(clean, tmp_path):
    root, truth, ref = clean
    bg = load_session(root).read(load_session(root).background_images[0])

    def erase_band(i, img):
        if i != 4:
            return img
        out = img.copy()
        out[110:130] = bg[110:130]  # the specimen vanishes in a horizontal band of view 4
        return out

    bad_root = _copy_with(root, tmp_path / "bad", erase_band)
    strict = reconstruct(bad_root, voxel_size=2.0)
    tolerant = reconstruct(bad_root, voxel_size=2.0, tolerance=1)
    # the bad view cuts a slab out of the model; with one view allowed to disagree
    # every voxel of the clean hull is back, at the price of a looser hull (each voxel
    # may ignore its most restrictive view: measured +3.85 % / +3.78 % with 12 views; the strict hull lost 32.5 % /
    # 32.6 % of the clean one)
    lost = ref.occupancy & ~strict.occupancy
    assert lost.sum() > 0.03 * ref.occupancy.sum()
    assert np.all(tolerant.occupancy[ref.occupancy])
    assert ref.mesh.volume < tolerant.mesh.volume < 1.05 * ref.mesh.volume
    assert tolerant.mesh.is_watertight
    report = json.loads(json.dumps(tolerant.report))
    assert report["mesh_volume_error_pct"] == pytest.approx(100 * (tolerant.mesh.volume / truth["volume_mm3"] - 1))
