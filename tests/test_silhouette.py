import numpy as np
import pytest

from organlab.silhouette import (
    auto_threshold,
    background_model,
    background_noise,
    clean_mask,
    coverage,
    difference,
    silhouette,
)

H, W = 120, 160


def _scene(rng, noise=2.0, ss=8):
    """Background gradient + a textured disk (anti-aliased by supersampling)."""
    yy, xx = np.mgrid[0:H, 0:W]
    bg = np.stack([30 + 0.2 * xx, 40 + 0.1 * yy, 60 + 0 * xx], axis=-1).astype(np.float64)
    cx, cy, r = 80.3, 58.7, 30.2
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    cov = np.zeros((H, W))
    for dy in sub:
        for dx in sub:
            cov += ((xx + dx - cx) ** 2 + (yy + dy - cy) ** 2) <= r * r
    cov /= ss * ss
    tex = np.stack([170 + 30 * np.sin(xx / 5.0), 90 + 20 * np.cos(yy / 7.0), 80 + 0 * xx], axis=-1)
    clean = cov[..., None] * tex + (1 - cov[..., None]) * bg

    def noisy(img):
        return np.clip(img + rng.normal(0, noise, img.shape), 0, 255).round().astype(np.uint8)

    frames = [noisy(bg) for _ in range(10)]
    return frames, noisy(clean), cov, np.pi * r * r


def test_background_model_reduces_noise():
    rng = np.random.default_rng(0)
    frames, _, _, _ = _scene(rng, noise=4.0)
    truth = _scene(np.random.default_rng(0), noise=0.0)[0][0].astype(np.float32)
    for method in ("median", "mean"):
        bg = background_model(frames, method=method)
        assert bg.dtype == np.float32 and bg.shape == (H, W, 3)
        # one frame's noise is 4 levels; the model of 10 frames is well under it
        assert np.sqrt(((bg - truth) ** 2).mean()) < 2.0
    with pytest.raises(ValueError, match="median"):
        background_model(frames, method="mode")
    with pytest.raises(ValueError, match="differ in shape"):
        background_model([frames[0], frames[0][:10]])


def test_silhouette_matches_the_rendered_disk():
    rng = np.random.default_rng(1)
    frames, img, cov, area = _scene(rng)
    bg = background_model(frames)
    s = silhouette(img, bg)
    truth = cov >= 0.5
    # only pixels on the anti-aliased rim may disagree
    wrong = s.mask != truth
    assert wrong.sum() <= 0.02 * truth.sum()
    assert np.all((cov[wrong] > 0.05) & (cov[wrong] < 0.95))
    # sub-pixel coverage measures the disk's area better than the binary mask
    assert abs(s.coverage.sum() - area) < 0.01 * area
    assert abs(s.coverage.sum() - area) < abs(s.mask.sum() - area) + 1.0
    assert 5 < s.threshold < 100


def test_threshold_given_and_grey_mode():
    rng = np.random.default_rng(2)
    frames, img, cov, _ = _scene(rng)
    bg = background_model(frames)
    d = difference(img, bg, mode="grey")
    assert d.shape == (H, W) and d[cov == 0].mean() < 3 and d[cov == 1].mean() > 40
    s = silhouette(img, bg, threshold=20.0)
    assert s.threshold == 20.0
    assert (s.mask != (cov >= 0.5)).sum() < 0.03 * (cov >= 0.5).sum()
    t = auto_threshold(difference(img, bg))
    assert d[cov == 0].max() < t or t > 10


def test_clean_mask_removes_noise_and_fills_holes():
    m = np.zeros((H, W), bool)
    m[30:90, 40:120] = True
    raw = m.copy()
    raw[50:53, 60:63] = False  # a hole
    raw[5, 5] = raw[100, 150] = raw[110, 20] = True  # salt
    raw[10:14, 140:144] = True  # a small blob, 16 px
    out = clean_mask(raw)
    # opening rounds the rectangle's four corner pixels off; nothing else differs
    diff = np.argwhere(out != m)
    assert len(diff) <= 4 and all(tuple(p) in {(30, 40), (30, 119), (89, 40), (89, 119)} for p in diff)
    # a second large component is kept
    raw2 = m.copy()
    raw2[100:115, 10:40] = True
    assert clean_mask(raw2)[105, 20]
    # an all-empty mask stays empty
    assert not clean_mask(np.zeros((H, W), bool)).any()


def test_coverage_of_a_blended_edge():
    # a vertical edge at column 10.3: column 10 is covered 70 % by the specimen
    bg = np.full((20, 20, 3), 30.0, np.float32)
    fg = np.array([200.0, 120.0, 60.0])
    img = np.tile(bg, (1, 1, 1)).copy()
    img[:, 11:] = fg
    img[:, 10] = 0.7 * fg + 0.3 * 30.0
    mask = np.zeros((20, 20), bool)
    mask[:, 10:] = True
    c = coverage(img.round().astype(np.uint8), bg, mask)
    np.testing.assert_allclose(c[:, 10], 0.7, atol=0.01)
    assert (c[:, 12:] == 1).all() and (c[:, :9] == 0).all()
    with pytest.raises(ValueError, match="differ in size"):
        coverage(img, bg, mask[:5])


def test_constant_difference_is_an_error():
    with pytest.raises(ValueError, match="constant"):
        auto_threshold(np.zeros((10, 10)))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_difference_is_an_error(bad):
    """One NaN or infinity anywhere among finite values is refused (auto_threshold reads it from the
    minimum and maximum, without an isfinite pass)."""
    d = np.random.default_rng(0).random((12, 9)).astype(np.float32) * 50
    d[7, 4] = bad
    with pytest.raises(ValueError, match="non-finite"):
        auto_threshold(d)


def test_warm_kernels_load_the_specialisations_the_stage_calls():
    """``warm_kernels`` (the reconstruct command runs it on a thread while the session loads) must load the
    very specialisations the stage then calls: a tiny input of another dtype or layout would load one the
    stage never uses and leave the real one (and numba's 0.5 s registry load) to the stage."""
    from organlab.silhouette import _kernels, warm_kernels

    warm_kernels()
    kernels = (_kernels.std_frames, _kernels.color_distance, _kernels.split_above)  # median <= 32 frames: numpy
    before = [list(k.signatures) for k in kernels]
    assert all(before)
    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 256, (12, 16, 3), dtype=np.uint8) for _ in range(4)]
    bg = background_model(frames)
    background_noise(frames)
    auto_threshold(difference(frames[0], bg))
    assert [list(k.signatures) for k in kernels] == before  # nothing new compiled or loaded by the stage


@pytest.mark.parametrize("n", [1, 2, 3, 6, 19, 20, 32, 33, 40])
def test_median_frames_equals_numpy_median(n):
    """Both ways of the background median (the numpy selection network up to 32 frames, the numba
    histogram above) give numpy's median exactly, odd and even counts; the frames are left as they were."""
    from organlab.silhouette._kernels import median_frames

    rng = np.random.default_rng(n)
    stack = rng.integers(0, 256, (n, 997), dtype=np.uint8)
    stack[:, :50] = rng.integers(100, 103, (n, 50))  # ties, as in real frames that differ by noise
    copy = stack.copy()
    got = median_frames(stack)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, np.median(stack, axis=0).astype(np.float32))
    np.testing.assert_array_equal(stack, copy)


def _li_images():
    """Difference images Li's threshold is taken of: this file's scenes (two seeds, two noise levels), the
    sample's first views when present, and float32 images of other laws (skewed, bimodal, few levels,
    strided) that no default was tuned on."""
    rng = np.random.default_rng(11)
    out = []
    for seed, noise in [(2, 2.0), (5, 6.0)]:
        frames, img, _, _ = _scene(np.random.default_rng(seed), noise=noise)
        bg = background_model(frames)
        out += [difference(img, bg), difference(img, bg, mode="grey")]
    out.append(rng.exponential(3.0, (240, 320)).astype(np.float32))
    out.append(np.concatenate([rng.normal(5, 1, 20000), rng.normal(60, 9, 3000)]).astype(np.float32).reshape(100, 230))
    out.append(rng.integers(0, 7, (50, 60)).astype(np.float32) * np.float32(0.3))
    out.append(rng.gamma(2.0, 4.0, (300, 200)).astype(np.float32)[::2, ::3])  # not contiguous
    from pathlib import Path

    sample = Path(__file__).resolve().parents[1] / "sample_sessions" / "aaa_phantom"
    if (sample / "session.json").is_file():
        from organlab.session import load_session

        s = load_session(sample)
        bg = background_model([s.read(p) for p in s.background_images])
        out += [difference(s.read(v.image), bg) for v in s.views[:6]]
    return out


def test_li_threshold_is_scikit_images_to_the_bit():
    """auto_threshold's own Li iteration (one-pass split, sorted gaps) returns the very float32 that
    ``skimage.filters.threshold_li`` returns, on every image of _li_images: a threshold one ulp off could
    flip a pixel and change the silhouettes, which must stay byte-identical."""
    from skimage.filters import threshold_li

    from organlab.silhouette._subtract import _li_threshold

    for d in _li_images():
        want = threshold_li(d)
        got = _li_threshold(np.asarray(d, dtype=np.float32))
        assert got.dtype == want.dtype == np.float32
        assert got == want
        assert auto_threshold(d) == float(want)


def test_default_silhouettes_import_no_skimage_filters():
    """Li's threshold (the default) is our own: the silhouettes of the sample import neither skimage.filters nor
    scipy.ndimage (82 modules, 0.15-0.2 s CPU that both silhouette threads waited on in the command, issue 24);
    'otsu' still reads skimage's (and imports it).  In a new process, 6 of the sample's views."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    code = ("import sys\nimport organlab as ol\nfrom organlab.silhouette import SilhouetteModel, auto_threshold\n"
            "s = ol.load_session('sample_sessions/aaa_phantom')\n"
            "model = SilhouetteModel.from_session(s, views=range(6))\n"
            "assert all(x.mask.any() for x in model.silhouettes())\n"
            "print('LI', 'skimage.filters' in sys.modules, 'scipy.ndimage' in sys.modules)\n"
            "auto_threshold(model.differences[0], method='otsu')\n"
            "print('OTSU', 'skimage.filters' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=root).stdout
    assert "LI False False" in out, out
    assert "OTSU True" in out, out
