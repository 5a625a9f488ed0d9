"""Visual-hull carving: the thesis's bounding-box test (reference), its fast
coarse-to-fine version (voxel for voxel the same), tolerance, progressive
carving, and the hull of a sphere against its analytic volume."""

import numpy as np
import pytest

from organlab.camera import Camera
from organlab.carving import ProgressiveCarver, carve, carve_reference
from organlab.carving._bbox import _corner_axes, _exact_carved, _reference_counts, _sat
from organlab.grid import VoxelGrid


# ------------------------------------------------------------------ helpers
def look_at(centre, target=(0.0, 0.0, 0.0), *, f=300.0, size=(96, 72), dist=None, skew=0.0):
    """Camera at ``centre`` looking at ``target`` (OpenCV axes, Z up in the world)."""
    c = np.asarray(centre, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    w, h = size
    K = [[f, skew * f, (w - 1) / 2 + 0.37], [0.0, 1.01 * f, (h - 1) / 2 - 0.21], [0.0, 0.0, 1.0]]
    return Camera(K, dist, R, -R @ c, size)


def ring(n, radius, height, *, target=(0.0, 0.0, 0.0), phase=0.0, **kw):
    angles = phase + np.arange(n) * 2 * np.pi / n
    return [look_at((radius * np.cos(a), radius * np.sin(a), height), target, **kw) for a in angles]


def sphere_mask(camera, centre, radius):
    """Silhouette of a sphere: a pixel is inside if its ray hits the sphere."""
    w, h = camera.image_size
    uu, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    o, d = camera.rays(np.stack([uu.ravel(), vv.ravel()], axis=1))
    oc = o - np.asarray(centre, float)
    b = np.einsum("ij,ij->i", oc, d)
    disc = b * b - (np.einsum("ij,ij->i", oc, oc) - radius**2)
    hit = (disc >= 0) & (-b + np.sqrt(np.maximum(disc, 0.0)) > 0)
    return hit.reshape(h, w)


def blob_masks(cameras, rng, *, density=0.5, noise=0.02):
    """Random silhouettes: coarse random blocks plus salt noise."""
    masks = []
    for cam in cameras:
        w, h = cam.image_size
        coarse = rng.random((h // 6 + 1, w // 6 + 1)) < density
        m = np.kron(coarse, np.ones((6, 6), bool))[:h, :w]
        masks.append(m | (rng.random((h, w)) < noise))
    return masks


def brute_force(masks, cameras, grid):
    """The thesis's test, voxel by voxel, straight from its definition."""
    ax = _corner_axes(grid)
    occ = np.ones(grid.shape, bool)
    for idx in np.ndindex(grid.shape):
        corners = np.array(
            [[ax[0][idx[0] + i], ax[1][idx[1] + j], ax[2][idx[2] + k]] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
        )
        for m, cam in zip(masks, cameras):
            with np.errstate(all="ignore"):
                uv = cam.project(corners)
            if np.isnan(uv).any():
                continue  # a corner behind the camera: this view does not carve
            c0, c1 = np.ceil(uv[:, 0].min() - 0.5), np.floor(uv[:, 0].max() + 0.5)
            r0, r1 = np.ceil(uv[:, 1].min() - 0.5), np.floor(uv[:, 1].max() + 0.5)
            if c0 < 0 or r0 < 0 or c1 > cam.width - 1 or r1 > cam.height - 1:
                continue  # reaches outside the image: unknown, not carved
            if not m[int(r0) : int(r1) + 1, int(c0) : int(c1) + 1].any():
                occ[idx] = False
                break
    return occ


DIST = [-0.25, 0.08, 1.5e-3, -1e-3, 0.01]


# -------------------------------------------------------------- reference
def test_reference_is_the_thesis_test():
    rng = np.random.default_rng(1)
    grid = VoxelGrid((-5.0, -4.0, -6.0), 1.3, (8, 7, 9))
    cams = ring(4, 60.0, 20.0, f=250.0, size=(64, 48), dist=DIST, skew=0.01)
    cams.append(look_at((0.0, 0.0, 3.0), (0.0, 10.0, 3.0), f=60.0, size=(64, 48)))  # inside the grid
    cams.append(look_at((0.0, -25.0, 0.0), f=400.0, size=(64, 48)))  # sees only part of the grid
    masks = [rng.random((48, 64)) < 0.03 for _ in cams]
    expected = brute_force(masks, cams, grid)
    got = carve_reference(masks, cams, grid, chunk_voxels=37)
    assert 0 < expected.sum() < expected.size
    np.testing.assert_array_equal(got, expected)


def test_exact_path_matches_reference():
    # the fallback carve uses for undecided voxels is the reference test
    rng = np.random.default_rng(2)
    grid = VoxelGrid((-6.0, -6.0, -6.0), 1.0, (12, 12, 12))
    cam = look_at((0.0, -40.0, 5.0), f=120.0, size=(64, 48), dist=DIST)
    mask = blob_masks([cam], rng)[0]
    counts = _reference_counts([mask], [cam], grid, 10**6)
    flat = np.arange(grid.n_voxels)
    carved = _exact_carved(flat, grid, _corner_axes(grid), _sat(mask), cam, 1)
    np.testing.assert_array_equal(carved.reshape(grid.shape), counts == 1)


# ------------------------------------------------------------ exactness
def _scene(name, rng):
    if name == "sphere-distorted":
        grid = VoxelGrid.from_roi((-22, -22, -22), (22, 22, 22), 1.0)
        cams = ring(8, 250.0, 80.0, f=400.0, dist=DIST) + ring(5, 250.0, -120.0, f=400.0, dist=DIST, phase=0.3)
        masks = [sphere_mask(c, (1.0, -2.0, 0.5), 15.0) for c in cams]
    elif name == "random-blobs":
        grid = VoxelGrid((-15.0, -12.0, -10.0), 0.9, (33, 27, 23))
        cams = ring(7, 120.0, 30.0, f=250.0, dist=DIST, skew=0.02)
        masks = blob_masks(cams, rng)
    elif name == "border-and-near":
        # the grid overflows the images; one camera stands inside the grid
        grid = VoxelGrid((-30.0, -30.0, -20.0), 1.5, (41, 37, 30))
        cams = ring(6, 70.0, 10.0, f=90.0, dist=DIST)
        cams.append(look_at((2.0, 3.0, 1.0), (30.0, 3.0, 1.0), f=40.0))
        masks = blob_masks(cams, rng, density=0.7, noise=0.05)
    elif name == "half-pixel-aligned":
        # axis-aligned pinhole cameras, principal point on a pixel edge: many
        # box edges fall exactly on pixel edges
        grid = VoxelGrid((-7.5, -7.5, -7.5), 1.0, (16, 16, 16))
        cams = []
        for c in ([0.0, -100.0, 0.0], [100.0, 0.0, 0.0], [0.0, 0.0, 100.0]):
            cam = look_at(c, f=200.0, size=(64, 64))
            K = np.array(cam.K)
            K[0, 1], K[0, 2], K[1, 1], K[1, 2] = 0.0, 31.5, 200.0, 31.5
            cams.append(Camera(K, None, cam.R, cam.t, (64, 64)))
        masks = [sphere_mask(c, (0.0, 0.0, 0.0), 6.3) for c in cams]
    else:
        raise KeyError(name)
    return grid, cams, masks


SCENES = ["sphere-distorted", "random-blobs", "border-and-near", "half-pixel-aligned"]


@pytest.mark.parametrize("name", SCENES)
def test_carve_equals_reference(name):
    grid, cams, masks = _scene(name, np.random.default_rng(3))
    ref = carve_reference(masks, cams, grid)
    got = carve(masks, cams, grid)
    assert 0 < ref.sum() < ref.size
    assert got.dtype == bool and got.shape == grid.shape
    np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("name", ["random-blobs", "border-and-near"])
@pytest.mark.parametrize("tolerance, min_pixels", [(1, 1), (2, 1), (0, 4), (1, 3)])
def test_carve_options_equal_reference_counts(name, tolerance, min_pixels):
    grid, cams, masks = _scene(name, np.random.default_rng(4))
    counts = _reference_counts(masks, cams, grid, 10**6, min_pixels)
    got = carve(masks, cams, grid, tolerance=tolerance, min_pixels=min_pixels)
    np.testing.assert_array_equal(got, counts <= tolerance)
    if tolerance == 0:
        np.testing.assert_array_equal(got, carve_reference(masks, cams, grid, min_pixels=min_pixels))


def test_inputs_not_modified_and_numeric_masks_accepted():
    grid, cams, masks = _scene("random-blobs", np.random.default_rng(5))
    before = [m.copy() for m in masks]
    a = carve(masks, cams, grid)
    b = carve([m.astype(np.uint8) * 255 for m in masks], cams, grid)
    np.testing.assert_array_equal(a, b)
    for m, m0 in zip(masks, before):
        np.testing.assert_array_equal(m, m0)


# ----------------------------------------------------------------- sphere
def test_sphere_hull_contains_sphere_and_volume_close():
    """The hull of a sphere seen by 26 cameras on three rings and the poles.

    Kept: every voxel whose centre is inside the sphere.  (Its projected
    centre p lies inside the sphere's convex silhouette; the voxel's box
    contains a disc of radius rho >= 1 px around p, so it covers every pixel
    centre within rho + 0.5 px of p, and one pixel centre inside the
    silhouette lies within sqrt(2) px of p.)

    Volume: the bounding-box test keeps voxels up to about one projected
    voxel box plus one pixel outside the view cones: the hull lies within a
    shell ``delta = sqrt(3) h + 2 px`` of the views' ideal visual hull, which
    itself lies within ``r / cos(theta / 2)`` of the centre for views
    ``theta`` apart.
    """
    c, r, h = np.array([1.0, -2.0, 0.5]), 15.0, 1.0
    D, f = 250.0, 400.0
    grid = VoxelGrid.from_roi(c - 22, c + 22, h)
    cams = ring(8, D, 0.0, target=c, f=f, dist=[-0.05, 0.0, 0.0, 0.0, 0.0])
    cams += ring(8, D * np.cos(0.7), D * np.sin(0.7), target=c, f=f, phase=0.4)
    cams += ring(8, D * np.cos(0.7), -D * np.sin(0.7), target=c, f=f, phase=0.4)
    cams += [look_at(c + [0.0, 0.0, D], c, f=f), look_at(c - [0.0, 0.0, D], c, f=f)]
    masks = [sphere_mask(cm, c, r) for cm in cams]
    occ = carve(masks, cams, grid)
    centres = grid.centers().reshape(*grid.shape, 3)
    inside = np.linalg.norm(centres - c, axis=-1) < r
    assert np.all(occ[inside]), "a voxel whose centre is inside the sphere was carved"
    px_mm = (D + r) / f  # pixel size at the far side of the sphere, mm
    theta = 2 * np.pi / 8  # the coarsest angular spacing of the views
    delta = np.sqrt(3) * h + 2 * px_mm
    r_out = r / np.cos(theta / 2) + delta
    V, V_true = grid.volume_of(occ), 4 / 3 * np.pi * r**3
    assert V > 0.97 * V_true
    assert V < 4 / 3 * np.pi * r_out**3
    # and no kept voxel is farther than r_out from the centre
    assert np.linalg.norm(centres[occ] - c, axis=-1).max() < r_out


# -------------------------------------------------------------- tolerance
def test_tolerance_survives_corrupted_masks():
    c, r = np.array([0.0, 0.0, 0.0]), 12.0
    grid = VoxelGrid.from_roi(c - 16, c + 16, 0.8)
    cams = ring(10, 200.0, 60.0, f=300.0, dist=DIST) + ring(6, 200.0, -90.0, f=300.0, phase=0.2)
    clean = [sphere_mask(cm, c, r) for cm in cams]
    k = 2
    corrupted = [m.copy() for m in clean]
    for i in (1, 7):  # punch a hole in the middle of two silhouettes
        vv, uu = np.nonzero(corrupted[i])
        cu, cv = uu.mean(), vv.mean()
        h, w = corrupted[i].shape
        yy, xx = np.mgrid[:h, :w]
        corrupted[i][(xx - cu) ** 2 + (yy - cv) ** 2 < 6.0**2] = False
    hull = carve(clean, cams, grid)
    broken = carve(corrupted, cams, grid)
    tolerant = carve(corrupted, cams, grid, tolerance=k)
    assert broken.sum() < hull.sum() - 50, "the holes should tunnel through the classic hull"
    # no voxel of the clean hull is lost with tolerance k ...
    assert np.all(tolerant[hull])
    # ... and tolerance adds only what k views carve: within the clean hull at tolerance k
    assert np.all(carve(clean, cams, grid, tolerance=k)[tolerant])
    # the added voxels are a thin shell: volume within 35 % of the clean hull
    assert tolerant.sum() < 1.35 * hull.sum()


# ------------------------------------------------------------ progressive
@pytest.mark.parametrize("tolerance", [0, 1])
def test_progressive_equals_batch(tolerance):
    grid, cams, masks = _scene("random-blobs", np.random.default_rng(6))
    batch = carve(masks, cams, grid, tolerance=tolerance)
    pc = ProgressiveCarver(grid, tolerance=tolerance)
    assert pc.n_views == 0 and pc.occupancy.all()
    previous = pc.occupancy
    for i in np.random.default_rng(7).permutation(len(cams)):
        occ = pc.add_view(masks[i], cams[i])
        assert not np.any(occ & ~previous), "adding a view never adds voxels"
        previous = occ
    assert pc.n_views == len(cams)
    np.testing.assert_array_equal(pc.occupancy, batch)
    assert pc.carve_counts.max() <= tolerance + 1


# ------------------------------------------------------------- bad input
def _bad_cases():
    grid = VoxelGrid((0.0, 0.0, 0.0), 1.0, (4, 4, 4))
    cam = look_at((0.0, -50.0, 0.0), f=100.0, size=(32, 24))
    m = np.zeros((24, 32), bool)
    return [
        ("mismatch", ([m, m], [cam], grid), {}, ValueError, "2 masks but 1 cameras"),
        ("empty", ([], [], grid), {}, ValueError, "no views"),
        ("shape", ([np.zeros((32, 24), bool)], [cam], grid), {}, ValueError, "image_size"),
        ("3d mask", ([np.zeros((24, 32, 3), bool)], [cam], grid), {}, ValueError, "2-D"),
        ("str mask", ([np.full((24, 32), "a")], [cam], grid), {}, ValueError, "bool"),
        ("camera", ([m], ["cam"], grid), {}, TypeError, "Camera"),
        ("grid", ([m], [cam], (4, 4, 4)), {}, TypeError, "VoxelGrid"),
        ("tolerance", ([m], [cam], grid), {"tolerance": -1}, ValueError, "tolerance"),
        ("tolerance float", ([m], [cam], grid), {"tolerance": 0.5}, ValueError, "tolerance"),
        ("min_pixels", ([m], [cam], grid), {"min_pixels": 0}, ValueError, "min_pixels"),
    ]


@pytest.mark.parametrize("case", _bad_cases(), ids=lambda c: c[0])
def test_bad_inputs_raise(case):
    _, args, kw, exc, match = case
    with pytest.raises(exc, match=match):
        carve(*args, **kw)
    if "tolerance" not in kw:
        with pytest.raises(exc, match=match):
            carve_reference(*args, **kw)


def test_progressive_bad_inputs_raise():
    grid = VoxelGrid((0.0, 0.0, 0.0), 1.0, (4, 4, 4))
    cam = look_at((0.0, -50.0, 0.0), f=100.0, size=(32, 24))
    with pytest.raises(ValueError, match="tolerance"):
        ProgressiveCarver(grid, tolerance=-2)
    pc = ProgressiveCarver(grid)
    with pytest.raises(ValueError, match="image_size"):
        pc.add_view(np.zeros((10, 10), bool), cam)
    with pytest.raises(ValueError, match="chunk_voxels"):
        carve_reference([np.zeros((24, 32), bool)], [cam], grid, chunk_voxels=0)
    assert pc.n_views == 0
