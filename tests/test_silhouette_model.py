"""SilhouetteModel: prepared views re-run at a new threshold give what a fresh run gives.

On the bundled sample session (36 views, the automatic threshold tuned there) and
on a scene nothing was tuned on (test_silhouette's textured disk on a gradient,
noise of 4 grey levels, plus noise specks and a hole, touching the image border).
The box-cropped clean-up and coverage are checked against the same steps on the
whole image.
"""

import numpy as np
import pytest

from organlab.errors import SessionError
from organlab.silhouette import (
    SilhouetteModel,
    background_model,
    background_noise,
    clean_mask,
    coverage,
    session_silhouettes,
    silhouette,
)
from organlab.silhouette._subtract import _coverage_in, _disk, _fill_holes, _keep_components
from tests._shared_data import SAMPLE

H, W = 120, 160


def _same(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert np.array_equal(x.mask, y.mask) and np.array_equal(x.coverage, y.coverage)
        assert x.threshold == y.threshold and x.source == y.source


@pytest.mark.slow
def test_rethreshold_on_the_sample_equals_fresh_runs(sample_session):
    session = sample_session
    images = [session.read(v.image, key="x") for v in session.views]
    model = SilhouetteModel.from_session(session, images=images)
    _same(model.silhouettes(), session_silhouettes(session, images=images))
    for t in (9.0, 25.0, 14.0):
        again = model.silhouettes(threshold=t)
        _same(again, session_silhouettes(session, images=images, threshold=t))
        assert all(s.threshold == t for s in again)
    # a higher threshold shrinks every silhouette (so the masks really depend on it)
    lo, hi = model.silhouettes(threshold=9.0), model.silhouettes(threshold=25.0)
    assert all(h.mask.sum() <= l.mask.sum() for l, h in zip(lo, hi))
    assert sum(l.mask.sum() - h.mask.sum() for l, h in zip(lo, hi)) > 0


def _scene(rng, noise=4.0, ss=6):
    yy, xx = np.mgrid[0:H, 0:W]
    bg = np.stack([30 + 0.2 * xx, 40 + 0.1 * yy, 60 + 0 * xx], axis=-1).astype(np.float64)
    cx, cy, r = 20.3, 58.7, 30.2  # cut by the image's left edge
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    cov = np.zeros((H, W))
    for dy in sub:
        for dx in sub:
            d2 = (xx + dx - cx) ** 2 + (yy + dy - cy) ** 2
            cov += (d2 <= r * r) & ((xx + dx - 28) ** 2 + (yy + dy - 60) ** 2 > 36)  # with a hole
    cov /= ss * ss
    tex = np.stack([170 + 30 * np.sin(xx / 5.0), 90 + 20 * np.cos(yy / 7.0), 80 + 0 * xx], axis=-1)
    clean = cov[..., None] * tex + (1 - cov[..., None]) * bg

    def noisy(img):
        return np.clip(img + rng.normal(0, noise, img.shape), 0, 255).round().astype(np.uint8)

    frames = [noisy(bg) for _ in range(9)]
    views = [noisy(clean) for _ in range(3)]
    views[1][100:103, 120:123] = 250  # a speck far from the disk
    return frames, views


def test_rethreshold_on_an_unseen_scene_equals_fresh_runs():
    frames, views = _scene(np.random.default_rng(3))
    model = SilhouetteModel(views, frames)
    bg = background_model(frames)
    noise = background_noise(frames)  # the model keeps each view's dim rim down to 3 noise sigmas (grow_rim)
    floor = 5.0 * noise
    assert np.array_equal(model.background, bg)
    for t in (None, 20.0, 45.0):
        fresh = [silhouette(v, bg, threshold=t, floor=floor, noise=noise) for v in views]
        _same(model.silhouettes(threshold=t), fresh)
        _same(model.silhouettes(threshold=t, close_radius=0, fill_holes=False),
              [silhouette(v, bg, threshold=t, floor=floor, noise=noise, close_radius=0, fill_holes=False) for v in views])
    with pytest.raises(SessionError, match="threshold must be > 0"):
        model.silhouettes(threshold=0.0)
    with pytest.raises(SessionError, match="view 0: the silhouette is empty"):
        model.silhouettes(threshold=1000.0)
    # one view at a time (the viewer's per-view re-runs) gives the same silhouettes
    for t in (None, 20.0):
        _same([model.silhouette(i, threshold=t) for i in range(len(views))], model.silhouettes(threshold=t))
    with pytest.raises(SessionError, match="threshold must be > 0"):
        model.silhouette(0, threshold=-1.0)


def _clean_whole_image(mask, open_radius=1, close_radius=2, min_area_fraction=0.05, fill_holes=True):
    """clean_mask's steps on the whole image (no box), the yardstick of the cropped version."""
    import cv2

    m = mask.astype(np.uint8)
    if open_radius > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _disk(open_radius))
    if close_radius > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disk(close_radius))
    kept = _keep_components(m, min_area_fraction)
    if kept is None:
        return np.zeros(mask.shape, bool)
    return _fill_holes(kept) if fill_holes else kept


@pytest.mark.parametrize("seed", range(6))
def test_cropped_clean_up_and_coverage_equal_the_whole_image(seed):
    rng = np.random.default_rng(seed)
    # random blobs, specks and holes, some touching the border
    field = rng.normal(size=(H // 8 + 1, W // 8 + 1))
    import cv2

    smooth = cv2.resize(field, (W, H), interpolation=cv2.INTER_CUBIC)
    mask = (smooth > 0.6) ^ (rng.random((H, W)) < 0.02)
    for kw in ({}, {"close_radius": 4}, {"open_radius": 0, "fill_holes": False}, {"min_area_fraction": 0.5}):
        got = clean_mask(mask, **kw)
        assert np.array_equal(got, _clean_whole_image(mask, **kw))
    img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    bg = rng.uniform(0, 255, (H, W, 3)).astype(np.float32)
    m = clean_mask(mask)
    assert np.array_equal(coverage(img, bg, m), _coverage_in(img, bg, m.astype(np.uint8), 5))
    assert np.array_equal(coverage(img, bg, m, window=9), _coverage_in(img, bg, m.astype(np.uint8), 9))
