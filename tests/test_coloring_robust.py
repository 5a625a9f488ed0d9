"""Colouring without a cliff (issue 13): automatic threshold, exposure, robust measures, the silhouette guard.

The fast tests use test_coloring's tiny ray-cast scenes; the slow ones a
scene no default was tuned on (the dented, striped specimen under the hard
lamp, known cameras) and the real dinoSparseRing photos (skipped when
../shared/data is absent; the photos as a backdrop session are in test_real_dino.py).  Figures measured at 1 mm are in
docs/benchmarks.md; the tests use 2 mm.
"""


import numpy as np
import pytest

from organlab.coloring import PIPELINE_OPTIONS, color_voxels
from organlab.coloring._statistics import _shading_fit_std, _trimmed_std
from organlab.raster import model_mask
from tests._shared_data import DINO as DATA
from tests._shared_data import DINO_MISSING
from tests._shared_data import needs_dino
from tests.test_coloring import SLOT, _Boxes, _hull, _render, _ring, _smooth



@pytest.fixture(scope="module")
def slot():
    from organlab.grid import VoxelGrid

    scene = _Boxes(SLOT, _smooth)
    cams = _ring(n=16)
    images, masks = _render(scene, cams)
    grid = VoxelGrid.from_roi((-36, -36, 0.0), (36, 36, 72), 2.0)
    return cams, images, masks, grid, _hull(masks, cams, grid), scene.inside(grid.centers()).reshape(grid.shape)


def _unexplained(occ, hull, cams, masks, grid):
    """Silhouette pixels the hull's voxels cover but ``occ``'s do not, per view."""
    return [
        int((m & model_mask(hull, c, grid=grid) & ~model_mask(occ, c, grid=grid)).sum())
        for c, m in zip(cams, masks)
    ]


def test_guard_keeps_every_silhouette_pixel(slot):
    """At a threshold far too low, colouring carves through the silhouettes; the guard puts back what they need."""
    cams, images, masks, grid, hull, truth = slot
    bare = color_voxels(images, cams, hull, grid, masks=masks, threshold=0.5, support=1)
    lost = _unexplained(bare.occupancy, hull, cams, masks, grid)
    assert max(lost) > 0.05 * min(m.sum() for m in masks)  # measured: most of each silhouette
    guarded = color_voxels(images, cams, hull, grid, masks=masks, threshold=0.5, support=1, guard=True)
    assert _unexplained(guarded.occupancy, hull, cams, masks, grid) == [0] * len(cams)
    assert guarded.n_restored > 0 and not np.any(guarded.occupancy & ~hull)
    with pytest.raises(ValueError, match="guard=True needs"):
        color_voxels(images, cams, hull, grid, guard=True)


def test_automatic_threshold_and_exposure(slot):
    """Views with exposure gains of +-10 %: the gains are measured, and the automatic threshold opens the slot."""
    cams, images, masks, grid, hull, truth = slot
    gains = 1.0 + 0.1 * np.sin(np.arange(len(images)) * 1.7)
    dim = [np.clip(np.rint(im * g), 0, 255).astype(np.uint8) for im, g in zip(images, gains)]
    res = color_voxels(dim, cams, hull, grid, masks=masks, threshold="auto", exposure=True, guard=True)
    assert res.automatic and res.threshold > 0 and res.noise is not None
    g = np.array(res.gains)
    # measured: within 4.2 % of the true gains (up to one common factor; the textured box's voxels
    # show different texture on their faces in different views), correlation 0.95
    np.testing.assert_allclose(g / g.mean(), gains / gains.mean(), rtol=0.06)
    assert np.corrcoef(g, gains)[0, 1] > 0.9
    excess = hull & ~truth
    removed = 1 - (res.occupancy & excess).sum() / excess.sum()
    lost = (truth & ~res.occupancy).sum() / truth.sum()
    assert removed > 0.4 and lost < 0.01, (removed, lost)


def test_trimmed_and_shading_measures():
    """A highlight in one view does not make a voxel inconsistent; shading that follows the table angle neither."""
    V, M = 12, 3
    a = np.arange(V) * 2 * np.pi / V
    vis = np.full((V, M), 10, np.int32)
    col = np.zeros((V, M, 3))
    col[:, 0] = [120, 80, 60]  # constant colour ...
    col[4, 0] += 90  # ... with a highlight in view 4
    shade = 1.0 + 0.3 * np.cos(a - 0.7)  # Lambertian with the lamp on the camera
    col[:, 1] = shade[:, None] * [120, 80, 60]
    col[:, 2] = np.random.default_rng(0).uniform(40, 200, (V, 3))  # a lid over a concavity
    sums = col * vis[:, :, None]
    trim = _trimmed_std(vis, sums)
    assert trim[0] < 1e-9 and trim[2] > 20
    fit = _shading_fit_std(vis, sums, a)
    assert fit[0] < 1e-4 and fit[1] < 1e-4 and fit[2] > 20
    assert _trimmed_std(vis, sums)[1] > 10  # what the between-view spread calls shading


def test_automatic_support_grows_below_the_automatic_threshold():
    """support='auto': the plain support at and above median + AUTO_K MAD, one more per deviation below, at most 9."""
    from organlab.coloring._auto import AUTO_K, auto_support

    d = {"median": 3.5, "mad": 1.8}
    assert auto_support(3.5 + AUTO_K * 1.8, d, 3) == 3 and auto_support(40.0, d, 3) == 3
    assert auto_support(3.5 + (AUTO_K - 0.5) * 1.8, d, 3) == 4
    assert auto_support(0.5 * (3.5 + AUTO_K * 1.8), d, 3) == 7  # half the automatic threshold: z = 2.25
    assert auto_support(0.0, d, 3) == 9 and auto_support(5.0, {"median": None, "mad": None}, 3) == 3


# ------------------------------------------------- scenes no default saw (slow)
def _hard_scene(name, image_size=(640, 480)):
    """A specimen under the hard lamp: 24 views (640 x 480 unless given), exposure +-10 %, noise, JPEG 90; known
    cameras, 2 mm."""
    import cv2

    from organlab import synthetic as sy
    from organlab.carving import carve
    from organlab.grid import VoxelGrid
    from organlab.synthetic import _hard

    spec = sy.make_specimen(name)
    cams = [sy.default_camera(image_size).at_table_angle(a) for a in np.arange(24) * 15.0]
    images = []
    for i, c in enumerate(cams):
        rng = np.random.default_rng([7, i])
        img = _hard.exposure_gain(rng) * _hard.render_hard(c, supersample=1, specimen=spec)
        img = np.clip(np.rint(img + rng.normal(0, 1.5, img.shape)), 0, 255).astype(np.uint8)
        buf = cv2.imencode(".jpg", img[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])[1]
        images.append(cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1].copy())
    masks = [m >= 0.5 for m in sy.render_masks(spec, cams, supersample=1)]
    lo, hi = spec.bounds
    grid = VoxelGrid.from_roi((lo[0] - 8, lo[1] - 8, 0.0), (hi[0] + 8, hi[1] + 8, hi[2] + 12), 2.0)
    hull = carve(masks, cams, grid)
    truth = spec.inside(grid.centers()).reshape(grid.shape)
    return images, cams, masks, grid, hull, truth


def _half_auto_double(scene):
    """Excess removed and true volume lost at the automatic threshold, half and twice it (pipeline options)."""
    images, cams, masks, grid, hull, truth = scene
    excess = hull & ~truth
    assert (truth & ~hull).sum() == 0
    out, auto = {}, None
    for f in (1.0, 0.5, 2.0):
        r = color_voxels(images, cams, hull, grid, masks=masks, threshold="auto" if auto is None else f * auto, **PIPELINE_OPTIONS)
        auto = auto or r.threshold
        out[f] = (1 - (r.occupancy & excess).sum() / excess.sum(), (truth & ~r.occupancy).sum() / truth.sum(), r.support)
        print(f"x{f} t {r.threshold:.2f} support {r.support}: removed {out[f][0]:.3f}, lost {out[f][1]:.4f}")
    return out


@pytest.fixture(scope="module")
def dented():
    """The dented, striped specimen (issue 13's new specimen)."""
    return _hard_scene("dented")


@pytest.mark.slow
def test_dented_specimen_under_the_hard_lamp(dented):
    r = _half_auto_double(dented)
    # issue 13's targets: >= 50 % of the excess removed for <= 1 % lost at the automatic threshold (measured
    # 2 mm, 24 views: 60.6 %, 0.18 %; 1 mm, 36 views: see docs/benchmarks.md), and <= 2 % lost from half to
    # twice it: measured 0.88 % at half (support 'auto' -> 7; with the fixed support 3: 5.8 %), 0.15 % at twice
    assert r[1.0][0] >= 0.5 and r[1.0][1] <= 0.01 and r[1.0][2] == 3
    assert r[0.5][1] <= 0.02 and r[0.5][0] > 0.3 and r[0.5][2] > 3  # measured 47.3 % removed
    assert r[2.0][1] <= 0.02 and r[2.0][0] > 0.3  # measured 40.4 %


@pytest.mark.slow
def test_grooved_specimen_under_the_hard_lamp():
    """The same targets on a scene the automatic support's rule was not set on (the grooved specimen, hard lamp)."""
    r = _half_auto_double(_hard_scene("grooved", image_size=(480, 360)))
    # measured (2 mm, 24 views, 480 x 360): auto 63.7 % removed, 0.41 % lost; half 35.1 %, 1.29 %; twice 54.7 %,
    # 0.32 % (at 640 x 480: auto 58.3 %, 0.30 %; half 33.2 %, 1.25 % (fixed support 3: 5.7 %); twice 50.6 %,
    # 0.24 %; at 320 x 240 half lost 2.37 %: too coarse for the 2 % bound).  480 x 360 for CPU: 22.5 s (render 11.5)
    # against 29.9 s (render 17.9) at 640 x 480, under load
    assert r[1.0][0] >= 0.5 and r[1.0][1] <= 0.01
    assert r[0.5][1] <= 0.02 and r[2.0][1] <= 0.02
    assert r[0.5][0] > 0.2 and r[2.0][0] > 0.3




@pytest.fixture(scope="module")
def dino():
    if not (DATA / "dinoSR_par.txt").is_file():
        pytest.skip(DINO_MISSING)
    from organlab.datasets import load_middlebury, middlebury_silhouettes

    data = load_middlebury(DATA)
    good = np.nonzero(data.good)[0]
    imgs = [data.images[i] for i in good]
    return data, imgs, [data.cameras[i] for i in good], middlebury_silhouettes(imgs)


def _mean_iou(occ, grid, cams, masks):
    return np.mean([((r := model_mask(occ, c, grid=grid)) & m).sum() / (r | m).sum() for c, m in zip(cams, masks)])


@needs_dino
@pytest.mark.slow
def test_dino_colouring_keeps_the_model(dino):
    """Real photos, the authors' masks, 2 mm: both methods at the automatic threshold, and at a quarter of it."""
    from organlab.carving import hull_field
    from organlab.grid import VoxelGrid

    data, imgs, cams, masks = dino
    grid = VoxelGrid.from_roi(data.bbox[0] - 4.0, data.bbox[1] + 4.0, 2.0)
    hull = hull_field([m.astype(np.float32) for m in masks], cams, grid) >= 0.5
    h = _mean_iou(hull, grid, cams, masks)
    for method in ("voxel_coloring", "space_carving"):
        r = color_voxels(imgs, cams, hull, grid, masks=masks, method=method, threshold="auto", **PIPELINE_OPTIONS)
        # measured (2 mm): IoU 0.9445 vs the hull's 0.9440, 0.2 % of the hull's volume removed
        assert _mean_iou(r.occupancy, grid, cams, masks) > h - 0.01
        assert grid.volume_of(r.occupancy) > 0.97 * grid.volume_of(hull)
        low = color_voxels(imgs, cams, hull, grid, masks=masks, method=method, threshold=r.threshold / 4, **PIPELINE_OPTIONS)
        # the guard: no threshold carves through a silhouette (measured 0.9442 at a quarter)
        assert _unexplained(low.occupancy, hull, cams, masks, grid) == [0] * len(cams)
        assert _mean_iou(low.occupancy, grid, cams, masks) > h - 0.01


@needs_dino
@pytest.mark.slow
def test_dino_backdrop_keying_matches_the_authors_masks(dino):
    """The photos keyed against the border's colour (no masks, no frames) against the authors' recipe."""
    from organlab.silhouette import _keying

    data, imgs, cams, masks = dino
    colour = _keying.estimate_backdrop(imgs)
    ious = [(k & m).sum() / (k | m).sum() for k, m in ((_keying.key(im, colour)[0], m) for im, m in zip(imgs, masks))]
    # measured: mean 0.969, min 0.955 (the authors' masks are grown by 3 px; most of the rest is
    # their unfilled dark holes and the stand's top)
    assert np.mean(ious) > 0.96 and min(ious) > 0.945


