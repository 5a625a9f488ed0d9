"""A silhouette keeps its dim rim (organlab.silhouette.grow_rim, issue 21's "shading toward the rim").

Renders of AAA specimens the rim constants were not tuned on (shape seed 6; the constants were set on
``aaa-3``), 4 views of 320 x 240, their exact coverage from the same 2 x 2 samples per pixel:

* a rim-shaded, noisy render (a head lamp over a dark backdrop, ``look="rim"``, noise 3): Li's threshold
  cuts a band of the specimen along its outline; the hysteresis keeps it;
* an evenly lit noisy render, its exact masks (coverage >= 0.5) as seeds: nothing is added (a correct
  silhouette is not grown);
* the same with a soft shadow on the plate next to the specimen, dimmer than Li's threshold and far
  above the noise: it is not added;
* the last ring (``RIM_OUTER``: the outline's partly covered pixels, shaded more than the pixels inside
  them) is kept where the rim grew, and only there;
* live capture (``LiveHull.by_subtraction`` with the frames' noise) finds the same silhouettes as
  ``organlab reconstruct``.

The constants were chosen on ``aaa-3`` (36 views, 640 x 480, 1 mm); docs/silhouettes.md has the volumes.
"""

import numpy as np
import pytest

from organlab.silhouette import SilhouetteModel, background_model, background_noise, clean_mask, difference, grow_rim
from organlab.silhouette._subtract import RIM_FRACTION, RIM_OUTER
from organlab.synthetic import default_camera, make_specimen, render_lit, render_masks, render_view
from organlab.synthetic._render import quantize

SIZE, SS, N_VIEWS, SPEC = (320, 240), 2, 4, "aaa-6"


def _cams():
    cam0 = default_camera(SIZE)
    return [cam0.at_table_angle(360.0 * i / N_VIEWS + 10.0) for i in range(N_VIEWS)]


@pytest.fixture(scope="module")
def cover():
    return render_masks(SPEC, _cams(), supersample=SS)


@pytest.fixture(scope="module")
def rim_scene():
    cams = _cams()
    rng = np.random.default_rng(11)
    images = [quantize(render_lit(c, make_specimen(SPEC), look="rim", supersample=SS), 3.0, rng) for c in cams]
    empty = render_lit(cams[0], None, look="rim", supersample=SS)
    frames = [quantize(empty, 3.0, rng) for _ in range(6)]
    return images, frames


@pytest.fixture(scope="module")
def even_scene():
    cams = _cams()
    images = [render_view(SPEC, c, supersample=SS, noise_sigma=1.5, seed=[12, i]) for i, c in enumerate(cams)]
    empty = render_view(None, cams[0], supersample=SS)
    frames = [quantize(empty.astype(np.float64), 1.5, np.random.default_rng([13, j])) for j in range(6)]
    return images, frames


def _lost_and_grown(sils, cover):
    true = cover >= 0.5
    lost = np.array([np.count_nonzero(t & ~s.mask) for t, s in zip(true, sils)])
    grown = np.array([np.count_nonzero(s.mask & ~t) for t, s in zip(true, sils)])
    return lost, grown


def test_a_rim_shaded_view_keeps_its_rim(rim_scene, cover):
    images, frames = rim_scene
    model = SilhouetteModel(images, frames)
    on = model.silhouettes()
    model.rim_depth = 0
    off = model.silhouettes()
    lost_off, grown_off = _lost_and_grown(off, cover)
    lost_on, grown_on = _lost_and_grown(on, cover)
    # measured: Li's threshold alone loses 136-187 px per view of the exact mask (a band 1-3 px wide along
    # the outline at this size); with the rim kept 47-70 px (0.25-0.44 of it; 66-87 px, 0.35-0.53, without the
    # last ring: the outermost pixels, covered 0.5-0.7, show less than half their neighbours' difference);
    # outside the exact mask not one px more.
    assert lost_off.min() > 100, lost_off
    assert (lost_on <= 0.5 * lost_off).all(), (lost_on, lost_off)
    assert (grown_on <= grown_off).all(), (grown_on, grown_off)
    # what the hull sees: the coverage's sum against the exact coverage's, per view; measured -6.4 to -8.5 %
    # with Li's threshold alone, -1.1 to +0.4 % with the rim kept (near it, the edge pixels counted covered, the
    # pixels outside measured against their nearest specimen pixels; -1.5 to -0.1 % without the last ring):
    # 5.4-7.7 points better in every view
    err_off = np.array([s.coverage.sum() / c.sum() - 1 for s, c in zip(off, cover)])
    err_on = np.array([s.coverage.sum() / c.sum() - 1 for s, c in zip(on, cover)])
    assert (err_on > err_off + 0.035).all() and (np.abs(err_on) < 0.025).all(), (err_on, err_off)


def test_a_correct_silhouette_is_not_grown(even_scene, rim_scene, cover):
    for images, frames in (even_scene, rim_scene):
        bg = background_model(frames)
        noise = background_noise(frames)
        assert noise > 1.0  # the rule is on: it needs the background's noise
        for img, c in zip(images, cover):
            true = c >= 0.5
            grown = grow_rim(true, difference(img, bg), img, bg, noise=noise)
            # measured: 0 px added in every view of both renders (the pixels outside the exact mask are
            # covered < 0.5: they show under half the contrast of the pixels inside them)
            assert np.count_nonzero(grown & ~true) == 0
    # the evenly lit render's own silhouettes: the rim step adds nothing outside the exact masks (measured: 11-16
    # px per view outside them with or without it, pixels covered < 0.5 above Li's threshold; 1-3 px inside added)
    images, frames = even_scene
    model = SilhouetteModel(images, frames)
    on = model.silhouettes()
    model.rim_depth = 0
    off = model.silhouettes()
    assert np.array_equal(_lost_and_grown(on, cover)[1], _lost_and_grown(off, cover)[1])
    # nor its coverage beyond the exact (measured: -0.2 to -0.5 % per view against -0.9 to -1.4 % without the
    # step: the few pixels it adds make their neighbourhood's edge pixels count as covered)
    assert all(s.coverage.sum() <= c.sum() for s, c in zip(on, cover))


def test_a_shadow_is_not_added(even_scene, cover):
    images, frames = even_scene
    bg = background_model(frames)
    noise = background_noise(frames)
    img, c = images[1], cover[1]
    true = c >= 0.5
    # a soft shadow on the plate, below the specimen's foot: the plate darkened by up to 9 %
    ys, xs = np.nonzero(true)
    foot = ys.max()
    yy, xx = np.mgrid[: true.shape[0], : true.shape[1]]
    reach = np.clip(1.0 - (yy - foot) / 12.0, 0.0, 1.0) * ((xx >= xs.min()) & (xx <= xs.max()))
    shade = 1.0 - 0.09 * reach * (c < 0.01)
    shadowed = np.clip(np.rint(img * shade[..., None]), 0, 255).astype(np.uint8)
    shadow = (shade < 0.99) & (c == 0)
    diff = difference(shadowed, bg)
    model = SilhouetteModel([shadowed], frames)
    sil = model.silhouette(0)
    inner = diff[shadow & (yy <= foot + 3)]
    # the shadow is dimmer than Li's threshold and far above the noise (measured: up to 13 grey levels
    # against a threshold of 18 and a noise of 1.5): a rule on contrast alone would add it
    assert np.percentile(inner, 90) > 3 * noise * 1.5 and inner.max() < sil.threshold
    blind = grow_rim(clean_mask(diff > sil.threshold), diff, noise=noise)  # without the shadow test
    assert np.count_nonzero(blind & shadow) > 20
    assert np.count_nonzero(sil.mask & shadow) <= 2, np.count_nonzero(sil.mask & shadow)


def test_grow_rim_arguments():
    mask = np.zeros((5, 5), bool)
    mask[2, 2] = True
    diff = np.full((5, 5), 50.0, np.float32)
    assert np.array_equal(grow_rim(mask, diff, noise=0.0), mask)  # no noise figure: unchanged
    assert np.array_equal(grow_rim(mask, diff, noise=1.0, depth=0), mask)
    assert grow_rim(mask, diff, noise=1.0, depth=1).sum() == 9  # one ring
    with pytest.raises(ValueError, match="differ in size"):
        grow_rim(mask, diff[:4], noise=1.0)
    with pytest.raises(ValueError, match="fraction"):
        grow_rim(mask, diff, noise=1.0, fraction=0.0)
    frame = np.zeros((5, 5, 3), np.uint8)
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="rim_depth"):
            SilhouetteModel([frame], [frame], rim_depth=bad)


def test_keyed_views_are_not_changed(even_scene):
    """The rim step is background subtraction's: keyed views (a backdrop session, as the hard mode) are as before."""
    images, frames = even_scene
    model = SilhouetteModel(images, frames, backdrop={"color": "frames"})
    on = model.silhouettes()
    model.rim_depth = 0
    off = model.silhouettes()
    for a, b in zip(on, off):
        assert np.array_equal(a.mask, b.mask) and np.array_equal(a.coverage, b.coverage)


def test_the_last_ring_keeps_the_outline(rim_scene, even_scene, cover):
    """The last ring (grow_rim's ``outer``): on the rim render, the exact mask's outline pixels that the
    growth at ``fraction`` refused; on the exact masks and where nothing grew, nothing."""
    images, frames = rim_scene
    model = SilhouetteModel(images, frames)
    bg, noise = model.background, model.noise
    lost, grown = {}, {}
    for outer in (RIM_OUTER, RIM_FRACTION):  # RIM_FRACTION: no last ring (the step before)
        masks = []
        for img, d, t in zip(images, model.differences, model.auto_thresholds()):
            masks.append(grow_rim(clean_mask(d > t), d, img, bg, noise=noise, outer=outer))
        true = cover >= 0.5
        lost[outer] = np.array([np.count_nonzero(c & ~m) for c, m in zip(true, masks)])
        grown[outer] = np.array([np.count_nonzero(m & ~c) for c, m in zip(true, masks)])
    assert np.array_equal([s.mask for s in model.silhouettes()], [grow_rim(clean_mask(d > t), d, i, bg, noise=noise)
                          for i, d, t in zip(images, model.differences, model.auto_thresholds())])
    # measured: 47-70 px lost per view with the last ring against 66-87 px without (235 against 305 in all:
    # 0.77); not one px more outside the exact masks (4, 1, 8, 5 either way)
    assert lost[RIM_OUTER].sum() <= 0.85 * lost[RIM_FRACTION].sum(), lost
    assert np.array_equal(grown[RIM_OUTER], grown[RIM_FRACTION]), grown
    # the exact masks as seeds: nothing grows at ``fraction``, so no last ring either (0 px), even at an outer
    # fraction low enough to take most of the pixels next to them (0.1)
    for imgs, frs in (rim_scene, even_scene):
        b, n = background_model(frs), background_noise(frs)
        for img, c in zip(imgs, cover):
            true = c >= 0.5
            assert np.array_equal(grow_rim(true, difference(img, b), img, b, noise=n, outer=0.1), true)
    mask = np.zeros((5, 5), bool)
    mask[2, 2] = True
    with pytest.raises(ValueError, match="outer"):
        grow_rim(mask, np.ones((5, 5), np.float32), noise=1.0, outer=0.6)


def test_live_capture_keeps_the_rim(rim_scene, cover):
    """``LiveHull.by_subtraction`` with the frames' noise finds each view as ``organlab reconstruct`` does
    (SilhouetteModel: the rim kept); without it, Li's threshold alone."""
    from organlab.engine import LiveHull

    images, frames = rim_scene
    model = SilhouetteModel(images, frames)
    live = LiveHull.by_subtraction(model.background, floor=model.floor, noise=model.noise)
    plain = LiveHull.by_subtraction(model.background, floor=model.floor)
    true = cover >= 0.5
    for i, (img, c) in enumerate(zip(images, true)):
        sil = live(img)
        assert np.array_equal(sil.mask, model.silhouette(i).mask)
        assert np.allclose(sil.coverage, model.silhouette(i).coverage)
        # measured: 47-70 px of the exact mask lost with the rim kept, 136-187 without
        assert np.count_nonzero(c & ~sil.mask) <= 0.5 * np.count_nonzero(c & ~plain(img).mask)


@pytest.mark.slow  # about 7 s CPU (20 s on a loaded machine): 12 views rendered
def test_a_rim_shaded_hull_is_within_1_percent():
    """The volume: 12 rim-shaded views of ``aaa-6`` (320 x 240, noise 3, true cameras), the sub-voxel hull at 2 mm."""
    from organlab.carving import hull_field
    from organlab.grid import VoxelGrid

    n = 12
    cam0 = default_camera(SIZE)
    cams = [cam0.at_table_angle(360.0 * i / n + 10.0) for i in range(n)]
    spec = make_specimen(SPEC)
    rng = np.random.default_rng(11)
    images = [quantize(render_lit(c, spec, look="rim", supersample=SS), 3.0, rng) for c in cams]
    frames = [quantize(render_lit(cams[0], None, look="rim", supersample=SS), 3.0, rng) for _ in range(6)]
    grid = VoxelGrid.from_roi((-70, -70, 0), (70, 70, 200), 2.0)

    def error(sils):
        return hull_field(sils, cams, grid, sparse=True).n_inside() * grid.voxel_size**3 / spec.volume - 1

    model = SilhouetteModel(images, frames)
    on = error(model.silhouettes())
    seeds = [clean_mask(d > t) for d, t in zip(model.differences, model.auto_thresholds())]
    without = error([grow_rim(s, d, img, model.background, noise=model.noise, outer=RIM_FRACTION)
                     for s, d, img in zip(seeds, model.differences, images)])
    model.rim_depth = 0
    off = error(model.silhouettes())
    # measured: -0.48 % with the rim step (its last ring included), -1.72 % without the last ring, -11.3 % with
    # Li's threshold alone; the hull of the exact coverage is +1.91 % (it fills the concavities), so the
    # silhouettes are still 2.4 points under what exact ones give
    assert abs(on) < 0.01, on
    assert on > without + 0.009 and without < -0.012, (on, without)
    assert off < -0.08, off
