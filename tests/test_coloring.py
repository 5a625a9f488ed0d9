"""Tests of organlab.coloring: voxel colouring, space carving, the visibility check."""

from __future__ import annotations

import numpy as np
import pytest

from organlab.camera import Camera
from organlab.coloring import (
    DEFAULT_THRESHOLD,
    ColoringResult,
    VisibilityConstraintError,
    check_ordinal_visibility,
    color_voxels,
    voxel_colors,
)
from organlab.errors import OrganlabError
from organlab.grid import VoxelGrid

GREY = np.array([0.299, 0.587, 0.114])


# --------------------------------------------------------------- tiny scene
def _look_at(centre, target, size=(320, 240), f=520.0):
    centre = np.asarray(centre, float)
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    K = [[f, 0, size[0] / 2 - 0.5], [0, f, size[1] / 2 - 0.5], [0, 0, 1]]
    return Camera(K, [-0.05, 0.01, 0, 0, 0], R, -R @ centre, size)


def _ring(n=24, radius=260.0, height=190.0, target=(0.0, 0.0, 30.0), size=(320, 240)):
    """Cameras on a ring above the scene, looking at ``target`` (a turntable seen from one camera)."""
    cams = []
    for a in np.arange(n) * 2 * np.pi / n:
        cams.append(_look_at((radius * np.cos(a), radius * np.sin(a), height), target, size))
    return cams


class _Boxes:
    """A union of axis-aligned boxes with a colour given by a function of the surface point."""

    def __init__(self, boxes, albedo):
        self.boxes = [(np.array(lo, float), np.array(hi, float)) for lo, hi in boxes]
        self.albedo = albedo

    def inside(self, p):
        out = np.zeros(len(p), bool)
        for lo, hi in self.boxes:
            out |= np.all((p >= lo) & (p <= hi), axis=1)
        return out

    def hit(self, o, d):
        t_best = np.full(len(d), np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            for lo, hi in self.boxes:
                t1 = (lo - o) / d
                t2 = (hi - o) / d
                tn = np.nanmax(np.minimum(t1, t2), axis=1)
                tf = np.nanmin(np.maximum(t1, t2), axis=1)
                ok = (tn <= tf) & (tn > 0) & (tn < t_best)
                t_best[ok] = tn[ok]
        return t_best


def _render(scene, cams):
    """Flat-shaded ray casting (colour = albedo of the hit point), black background; images and masks."""
    images, masks = [], []
    for cam in cams:
        w, h = cam.image_size
        v, u = np.mgrid[0:h, 0:w]
        o, d = cam.rays(np.stack([u.ravel(), v.ravel()], axis=1).astype(float))
        t = scene.hit(o, d)
        hit = np.isfinite(t)
        img = np.zeros((h * w, 3))
        img[hit] = scene.albedo(o[hit] + t[hit, None] * d[hit])
        images.append(np.clip(np.rint(img), 0, 255).astype(np.uint8).reshape(h, w, 3))
        masks.append(hit.reshape(h, w))
    return images, masks


def _hull(masks, cams, grid):
    """Visual hull by a simple centre test (voxel centre inside every silhouette)."""
    c = grid.centers()
    keep = np.ones(len(c), bool)
    for m, cam in zip(masks, cams):
        uv = np.rint(cam.project(c)).astype(int)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < m.shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < m.shape[0])
        inside = np.zeros(len(c), bool)
        inside[ok] = m[uv[ok, 1], uv[ok, 0]]
        keep &= inside
    # one voxel of margin, as a real hull's bounding-box test leaves
    from scipy import ndimage

    return ndimage.binary_dilation(keep.reshape(grid.shape))


def _smooth(p):
    g = 120 + 70 * np.sin(p[:, 0] / 7.0 + 0.3) * np.cos(p[:, 1] / 9.0) + 30 * np.sin(p[:, 2] / 6.0)
    return np.stack([g, 0.7 * g + 30, 0.5 * g + 50], axis=1)


SLOT = [((-30, -30, 0), (-8, 30, 60)), ((8, -30, 0), (30, 30, 60)), ((-8, -30, 0), (8, 6, 60))]


@pytest.fixture(scope="module")
def slot_scene():
    """A textured 60 mm cube with a 16 mm wide, 24 mm deep vertical slot that silhouettes fill."""
    scene = _Boxes(SLOT, _smooth)
    cams = _ring()
    images, masks = _render(scene, cams)
    grid = VoxelGrid.from_roi((-36, -36, 0.0), (36, 36, 72), 2.0)
    hull = _hull(masks, cams, grid)
    truth = scene.inside(grid.centers()).reshape(grid.shape)
    return scene, cams, images, masks, grid, hull, truth


@pytest.fixture(scope="module")
def uniform_scene():
    colour = np.array([180.0, 90.0, 40.0])
    scene = _Boxes([((-25, -25, 0), (25, 25, 50))], lambda p: np.broadcast_to(colour, (len(p), 3)))
    cams = _ring(n=12)
    images, masks = _render(scene, cams)
    grid = VoxelGrid.from_roi((-31, -31, 0.0), (31, 31, 60), 2.0)
    hull = _hull(masks, cams, grid)
    truth = scene.inside(grid.centers()).reshape(grid.shape)
    return colour, cams, images, masks, grid, hull, truth


# ---------------------------------------------------- visibility constraint
def _cam_at(centre):
    return _look_at(centre, (0.0, 0.0, 0.0))


@pytest.mark.parametrize(
    "centres, expected",
    [
        ([(200, 0, 100), (0, 200, 150), (-200, 0, 60.5)], (2, True)),  # all above: sweep top down
        ([(200, 0, -80), (-200, 0, -10)], (2, False)),  # all below: bottom up
        ([(300, 0, 0), (250, 40, 30)], (0, True)),  # all beyond +x
    ],
)
def test_ordinal_sweep_found(centres, expected):
    cams = [_cam_at(c) for c in centres]
    assert check_ordinal_visibility(cams, (-50, -50, 0), (50, 50, 60)) == expected


def test_ordinal_visibility_refused_names_space_carving():
    cams = [_cam_at((200, 0, 100)), _cam_at((-200, 0, 30)), _cam_at((0, -200, -40))]
    with pytest.raises(VisibilityConstraintError, match="space_carving") as e:
        check_ordinal_visibility(cams, (-50, -50, 0), (50, 50, 60))
    assert isinstance(e.value, OrganlabError)
    assert "camera 2" in str(e.value) and "\n" not in str(e.value)


def test_color_voxels_refuses_camera_below_top(slot_scene):
    scene, cams, images, masks, grid, hull, truth = slot_scene
    low = _look_at((0.0, -260.0, 40.0), (0.0, 0.0, 30.0))  # below the cube's top (z = 60)
    with pytest.raises(VisibilityConstraintError, match="method='space_carving'"):
        color_voxels(images[:3] + images[:1], cams[:3] + [low], hull, grid)


def test_constraint_uses_hull_top_not_roi_top():
    """A camera below the roi's top but above the hull's top is fine."""
    grid = VoxelGrid.from_roi((-10, -10, 0), (10, 10, 100), 2.0)
    hull = np.zeros(grid.shape, bool)
    hull[3:7, 3:7, :10] = True  # up to z = 20 mm
    cam = _look_at((150.0, 0.0, 50.0), (0.0, 0.0, 10.0), size=(64, 48), f=60.0)
    img = np.zeros((48, 64, 3), np.uint8)
    res = color_voxels([img], [cam], hull, grid)
    assert res.sweep == "-z"


# ------------------------------------------------------------------ inputs
def _bad_calls(images, cams, hull, grid):
    return [
        (dict(images=images[:2], cameras=cams[:3]), ValueError, "one camera per image"),
        (dict(images=[images[0][:, :-1]] * 3, cameras=cams[:3]), ValueError, "image_size"),
        (dict(images=[images[0].astype(float)] * 3, cameras=cams[:3]), ValueError, "uint8"),
        (dict(occupancy=hull.astype(np.uint8)), ValueError, "bool"),
        (dict(occupancy=hull[:-1]), ValueError, "shape"),
        (dict(method="carve"), ValueError, "method"),
        (dict(start="box"), ValueError, "start"),
        (dict(threshold=-1), ValueError, "threshold"),
        (dict(completeness=0), ValueError, "completeness"),
        (dict(completeness=1.5), ValueError, "completeness"),
        (dict(support=0), ValueError, "support"),
        (dict(measure="max"), ValueError, "measure"),
        (dict(masks=[np.ones((2, 2), bool)] * 3), ValueError, "mask 0"),
        (dict(occupancy=None), ValueError, "start='hull'"),
    ]


def test_bad_inputs(slot_scene):
    scene, cams, images, masks, grid, hull, truth = slot_scene
    for change, exc, msg in _bad_calls(images, cams, hull, grid):
        kw = dict(images=images[:3], cameras=cams[:3], occupancy=hull, grid=grid)
        kw.update(change)
        args = [kw.pop(k) for k in ("images", "cameras", "occupancy", "grid")]
        with pytest.raises(exc, match=msg):
            color_voxels(*args, **kw)


def test_inputs_not_modified(uniform_scene):
    colour, cams, images, masks, grid, hull, truth = uniform_scene
    copies = [im.copy() for im in images], [m.copy() for m in masks], hull.copy()
    color_voxels(images, cams, hull, grid, masks=masks, threshold=5)
    assert all(np.array_equal(a, b) for a, b in zip(copies[0], images))
    assert all(np.array_equal(a, b) for a, b in zip(copies[1], masks))
    assert np.array_equal(copies[2], hull)


# ------------------------------------------------------------------ results
def test_uniform_colour_carves_no_true_voxel(uniform_scene):
    """A one-colour box is consistent everywhere: only background-seen voxels go, all outside the box."""
    colour, cams, images, masks, grid, hull, truth = uniform_scene
    res = color_voxels(images, cams, hull, grid, masks=masks, threshold=3)
    assert isinstance(res, ColoringResult)
    occ = res.occupancy
    assert occ.dtype == bool and occ.shape == grid.shape
    assert not np.any(occ & ~hull)
    assert np.count_nonzero(truth & ~occ) == 0
    assert res.n_carved == res.n_carved_background > 0
    assert np.count_nonzero(hull & ~truth & ~occ) == res.n_carved
    # the coloured voxels carry the box's colour exactly
    c = res.colors[res.colored].astype(float)
    assert len(c) > 500
    assert np.abs(c - colour).max() <= 1.0
    assert not res.colors[~res.colored].any()
    assert res.n_visible + res.n_hidden == np.count_nonzero(occ)


def test_grey_images(uniform_scene):
    colour, cams, images, masks, grid, hull, truth = uniform_scene
    grey = [np.rint(im @ GREY).astype(np.uint8) for im in images]
    res = color_voxels(grey, cams, hull, grid, masks=masks, threshold=3)
    c = res.colors[res.colored].astype(float)
    assert np.abs(c - colour @ GREY).max() <= 1.0
    assert np.count_nonzero(truth & ~res.occupancy) == 0


def test_voxel_coloring_carves_the_slot(slot_scene):
    scene, cams, images, masks, grid, hull, truth = slot_scene
    excess = hull & ~truth
    slot = excess & (np.abs(grid.centers()[:, 0]) < 8).reshape(grid.shape)
    assert np.count_nonzero(slot) > 300  # the silhouettes leave most of the slot filled
    # default threshold (tuned for shaded, noisy renders), and a tighter one
    # that suits these flat-shaded, noise-free images
    for threshold, least in ((DEFAULT_THRESHOLD, 0.5), (10.0, 0.7)):
        res = color_voxels(images, cams, hull, grid, masks=masks, threshold=threshold)
        occ = res.occupancy
        assert res.sweep == "-z"
        removed = 1 - np.count_nonzero(occ & slot) / np.count_nonzero(slot)
        lost = np.count_nonzero(truth & ~occ) / np.count_nonzero(truth)
        assert removed > least, (threshold, removed)
        assert lost < 0.005, (threshold, lost)
    # colours of the coloured true voxels: the texture at the voxel (2 mm voxels, smooth texture)
    col = res.colored & truth
    err = np.abs(res.colors[col].astype(float) @ GREY - _smooth(grid.centers()[col.ravel()]) @ GREY)
    assert err.mean() < 6, err.mean()


def test_without_colour_test_nothing_but_background_is_carved(slot_scene):
    """``completeness`` above any voxel's pixel count leaves every seen voxel untested."""
    scene, cams, images, masks, grid, hull, truth = slot_scene
    res = color_voxels(images, cams, hull, grid, masks=masks, completeness=10**9)
    assert res.n_carved == res.n_carved_background
    assert res.n_untested == res.n_visible > 0
    res2 = color_voxels(images, cams, hull, grid, masks=masks, completeness=0.999999)
    assert res2.n_carved == res2.n_carved_background
    assert np.array_equal(res.occupancy, res2.occupancy)


def test_threshold_zero_without_support_carves_more(slot_scene):
    scene, cams, images, masks, grid, hull, truth = slot_scene
    strict = color_voxels(images, cams, hull, grid, masks=masks, threshold=0.0, support=1)
    loose = color_voxels(images, cams, hull, grid, masks=masks, threshold=255.0)
    assert strict.n_carved > loose.n_carved
    assert loose.n_carved == loose.n_carved_background


def test_space_carving_carves_the_slot_with_any_cameras(slot_scene):
    """Space carving works where the layered sweep is refused (a camera below the top)."""
    scene, cams, images, masks, grid, hull, truth = slot_scene
    low = [_look_at((260 * np.cos(a), 260 * np.sin(a), 45.0), (0, 0, 30)) for a in (0.3, 2.4)]
    li, lm = _render(scene, low)
    cams2, images2, masks2 = cams + low, images + li, masks + lm
    with pytest.raises(VisibilityConstraintError):
        color_voxels(images2, cams2, hull, grid, masks=masks2)
    res = color_voxels(images2, cams2, hull, grid, masks=masks2, method="space_carving")
    assert res.sweep is None and res.iterations > 1
    slot = hull & ~truth & (np.abs(grid.centers()[:, 0]) < 8).reshape(grid.shape)
    occ = res.occupancy
    removed = 1 - np.count_nonzero(occ & slot) / np.count_nonzero(slot)
    lost = np.count_nonzero(truth & ~occ) / np.count_nonzero(truth)
    assert removed > 0.5, removed
    assert lost < 0.01, lost


def test_start_roi_with_masks_stays_near_the_box(uniform_scene):
    """From the whole grid, silhouettes and colour carve down to about the box, losing none of it."""
    colour, cams, images, masks, grid, hull, truth = uniform_scene
    res = color_voxels(images, cams, None, grid, start="roi", masks=masks, threshold=3)
    occ = res.occupancy
    assert res.n_candidates == grid.n_voxels
    assert np.count_nonzero(truth & ~occ) == 0
    # what is left outside the box is within the hull's margin
    assert np.count_nonzero(occ & ~hull) < 0.02 * np.count_nonzero(truth)


def test_voxel_colors_two_halves():
    """Colours of an occupancy, by exact visibility: the left half red, the right half blue."""
    red, blue = np.array([200.0, 40.0, 40.0]), np.array([30.0, 60.0, 210.0])
    scene = _Boxes([((-25, -25, 0), (25, 25, 50))], lambda p: np.where(p[:, :1] < 0, red, blue))
    cams = _ring(n=12)
    images, masks = _render(scene, cams)
    grid = VoxelGrid.from_roi((-30, -30, 0.0), (30, 30, 56), 2.0)
    occ = scene.inside(grid.centers()).reshape(grid.shape)
    colors = voxel_colors(images, cams, occ, grid, masks=masks)
    x = grid.centers()[:, 0].reshape(grid.shape)
    has = colors.any(axis=3)
    assert np.count_nonzero(has) > 1000
    assert not np.any(has & ~occ)
    left = has & (x < -3)
    right = has & (x > 3)
    assert np.abs(colors[left].astype(float) - red).max() <= 1
    assert np.abs(colors[right].astype(float) - blue).max() <= 1


# -------------------------------------------------------- done-when check
@pytest.mark.slow
def test_grooved_specimen_done_when():
    """Textured synthetic specimen with hidden pockets, 36 views, 640 x 480 px, 1 mm voxels.

    Colouring removes at least 60 % of the visual hull's excess volume (hull
    voxels outside the true solid) while losing at most 1 % of the true
    solid's voxels, and the voxel colours match the rendered images within 10
    grey levels on average.
    """
    sy = pytest.importorskip("organlab.synthetic")
    from organlab.carving import carve

    spec = sy.make_specimen("grooved")
    cam0 = sy.default_camera((640, 480))
    cams = [cam0.at_table_angle(a) for a in np.arange(36) * 10.0]
    images = [sy.render_view(spec, c, supersample=1, noise_sigma=1.0, seed=i) for i, c in enumerate(cams)]
    masks = [m >= 0.5 for m in sy.render_masks(spec, cams, supersample=1)]
    lo, hi = spec.bounds
    # the roi starts on the table (z = 0), as a session's does
    grid = VoxelGrid.from_roi((lo[0] - 8, lo[1] - 8, 0.0), (hi[0] + 8, hi[1] + 8, hi[2] + 12), 1.0)
    hull = carve(masks, cams, grid)
    truth = spec.inside(grid.centers()).reshape(grid.shape)
    excess = hull & ~truth
    assert np.count_nonzero(truth & ~hull) == 0
    assert np.count_nonzero(excess) > 0.08 * np.count_nonzero(truth)

    res = color_voxels(images, cams, hull, grid, masks=masks)
    occ = res.occupancy
    removed = 1 - np.count_nonzero(occ & excess) / np.count_nonzero(excess)
    lost = np.count_nonzero(truth & ~occ) / np.count_nonzero(truth)
    assert removed >= 0.60, removed
    assert lost <= 0.01, lost

    # Colours: each coloured true voxel against the images at the nearest
    # surface point, averaged over the views that see that point.
    rng = np.random.default_rng(0)
    idx = np.flatnonzero((res.colored & truth).ravel())
    idx = rng.choice(idx, size=min(3000, idx.size), replace=False)
    p = grid.centers()[idx]
    phi = np.arctan2(p[:, 1], p[:, 0])
    r = spec.star.radius(phi, p[:, 2])
    q = np.stack([r * np.cos(phi), r * np.sin(phi), p[:, 2]], axis=1)
    top = (hi[2] - p[:, 2]) < (r - np.hypot(p[:, 0], p[:, 1]))
    q[top, 2] = hi[2]
    q[top, :2] = p[top, :2]
    total = np.zeros((len(q), 3))
    count = np.zeros(len(q))
    for cam, img in zip(cams, images):
        d = q - cam.center
        dist = np.linalg.norm(d, axis=1)
        t, _ = spec.intersect(np.broadcast_to(cam.center, d.shape), d / dist[:, None])
        uv = np.rint(cam.project(q)).astype(int)
        ok = (np.abs(t - dist) < 0.3) & (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
        total[ok] += img[uv[ok, 1], uv[ok, 0]]
        count[ok] += 1
    seen = count > 0
    assert seen.mean() > 0.8
    rendered = total[seen] / count[seen, None]
    err = np.abs(res.colors.reshape(-1, 3)[idx[seen]].astype(float) @ GREY - rendered @ GREY)
    assert err.mean() <= 10.0, err.mean()
