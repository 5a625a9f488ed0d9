"""Issue 21: parts thinner than a voxel at 1 mm keep their shape through finish_surface.

Analytic scenes (no render): a 15 mm ball with three half-discs of radius 24 mm, 0.45-0.6 voxel thick (random
planes), a spherical cap and a tilted disc of other thicknesses, each as a coverage-like field (``0.5 - d``
clipped, its 0.5 level on the true surface) and as an occupancy (``d <= 0``).  Parts this thin come out of marching
cubes as two sheets a fraction of a voxel apart, perforated where the sampling misses them.

What finishing did to them (before ._thin.thin_vertices): smoothing took some vertices of a sheet through it, only
those went back to their raw places, and the remesher, starting from a sheet partly smoothed and partly raw, left
hundreds of faces below 20 degrees (1 573 on the coverage fins 0.6 thick, seed 0); the sliver step's cuts and
knife-edge flattening then left the surface 1.5-2 voxels off with angles of 0.03-0.16 degrees.  Now every vertex
of a part thinner than a voxel (and 4 rings around) starts from its raw place, the edge lengths still from the
smoothed surface.

Developed on seeds 0-2 (fins 0.4-0.9 voxel thick); the scenes below were not looked at before the rule was fixed.
"""

import numpy as np
import pytest

from organlab.grid import VoxelGrid
from organlab.surface import finish_surface, mesh_from_field, surface_deviation


def _field(d, voxel_size, kind):
    if kind == "coverage":
        return np.clip(0.5 - d / voxel_size, 0.0, 1.0).astype(np.float32)
    return d <= 0.0


def finned_ball(kind, thick, seed, *, voxel_size=1.0):
    """A 15 mm ball with three half-discs (radius 24 mm) ``thick`` voxels thick on random planes through its centre:
    ``(field, grid)``, ``kind`` 'coverage' (float32) or 'occupancy' (bool)."""
    n = int(60 / voxel_size) + 1
    grid = VoxelGrid(origin=(-30.0,) * 3, voxel_size=voxel_size, shape=(n, n, n))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    r = np.sqrt(x**2 + y**2 + z**2)
    d = r - 15.0  # signed distance, mm (exact off the fins' junctions)
    rng = np.random.default_rng(seed)
    for _ in range(3):
        a = rng.normal(size=3)
        a /= np.linalg.norm(a)
        e = np.cross(a, rng.normal(size=3))
        e /= np.linalg.norm(e)
        plate = np.abs(x * a[0] + y * a[1] + z * a[2]) - 0.5 * thick * voxel_size
        d = np.minimum(d, np.maximum.reduce([plate, r - 24.0, -(x * e[0] + y * e[1] + z * e[2])]))
    return _field(d, voxel_size, kind), grid


def capped_ball(kind, thick, *, voxel_size=1.0):
    """A 10 mm ball under a spherical cap ``thick`` voxels thick (radius 17 mm about (0, 0, -4) mm, above z = 5 mm)."""
    n = int(50 / voxel_size) + 1
    grid = VoxelGrid(origin=(-25.0,) * 3, voxel_size=voxel_size, shape=(n, n, n))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    rr = np.sqrt(x**2 + y**2 + (z + 4.0) ** 2)
    d = np.minimum(np.sqrt(x**2 + y**2 + z**2) - 10.0, np.maximum(np.abs(rr - 17.0) - 0.5 * thick * voxel_size, 5.0 - z))
    return _field(d, voxel_size, kind), grid


def disc_on_hub(kind, thick, *, voxel_size=1.0, axis=(0.3, 0.2, 0.93)):
    """A disc of radius 14 mm, ``thick`` voxels thick, tilted (normal ``axis``), through a 5 mm ball."""
    n = int(40 / voxel_size) + 1
    grid = VoxelGrid(origin=(-20.0,) * 3, voxel_size=voxel_size, shape=(n, n, n))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    r = np.sqrt(x**2 + y**2 + z**2)
    d = np.minimum(r - 5.0, np.maximum(np.abs(x * a[0] + y * a[1] + z * a[2]) - 0.5 * thick * voxel_size, r - 14.0))
    return _field(d, voxel_size, kind), grid


SCENES = {
    "fins coverage 0.6": lambda: finned_ball("coverage", 0.6, 3),
    "fins occupancy 0.45": lambda: finned_ball("occupancy", 0.45, 4),
    "cap coverage 0.6": lambda: capped_ball("coverage", 0.6),
    "disc occupancy 0.45": lambda: disc_on_hub("occupancy", 0.45),
}


# Measured (before thin_vertices -> with it -> with ._thin.thickened as well; max / mean deviation in voxels against
# the raw surface less its specks, smallest angle, volume change):
#   fins coverage 0.6 (seed 3)    1.907 / 0.133, 0.04 deg, -0.03 %  -> 0.684 / 0.051, 22.3 deg, -0.03 %
#                                 -> 0.631 / 0.065, 21.3 deg, +0.77 %
#   fins occupancy 0.45 (seed 4)  1.984 / 0.177, 0.03 deg, -1.51 %  -> 0.569 / 0.087, 23.2 deg, +0.07 %
#                                 -> 0.625 / 0.087, 21.7 deg, +0.08 %
#   cap coverage 0.6              1.520 / 0.114, 0.05 deg, -0.30 %  -> 0.656 / 0.049, 22.4 deg, -0.30 %
#                                 -> 0.467 / 0.067, 29.1 deg, +0.86 %
#   disc occupancy 0.45           1.777 / 0.217, 0.12 deg, -10.8 %  -> 0.505 / 0.075, 23.9 deg, +0.57 %
#                                 -> 0.503 / 0.076, 23.9 deg, +0.57 %
# Bounds: the promises (1 voxel max, 0.25 mean, 20 degrees, closed and manifold) with no last step needed (the
# remesher alone now keeps them: stay_on_data would hide a regression here; measured: none ran); volume within 1 %
# (measured 0.86 % at most: what thickening gives the coverage lace, whose raw volume is under the true one; the
# broken disc lost 10.8 %).
@pytest.mark.parametrize("scene", list(SCENES))
def test_parts_thinner_than_a_voxel_keep_their_shape(scene):
    from organlab.surface._repair import repair_mesh

    raw = mesh_from_field(*SCENES[scene]())
    fin = finish_surface(raw, voxel_size=1.0)
    names = [s["step"] for s in fin.steps]
    # the case is real: smoothing went through the part (the thin step ran and put vertices back)
    assert "thin" in names and fin.steps[names.index("thin")]["vertices_kept"] > 0, names
    assert "stay_on_data" not in names and "slivers" not in names, names
    reference, _ = repair_mesh(raw, speck_mm=3.0)  # the promise is stated against the raw surface less its specks
    dev = surface_deviation(fin.mesh, reference, voxel_size=1.0)
    assert dev["max_voxels"] < 1.0 and dev["mean_voxels"] < 0.25, dev
    assert fin.watertight and fin.final["min_angle_deg"] >= 20.0, fin.final["min_angle_deg"]
    assert fin.final["nonmanifold_edges"] == 0 and fin.final["boundary_edges"] == 0
    assert abs(fin.volume_change_pct) < 1.0, fin.volume_change_pct


def _plate_on_ball(half):
    """A plate ``2 * half`` mm thick (1 mm voxels, coverage field) on a 6 mm ball: the raw surface, and masks of its
    vertices on the plate's flat middle (off its rims) and on the ball away from the plate."""
    grid = VoxelGrid(origin=(-14.0,) * 3, voxel_size=1.0, shape=(29, 29, 29))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    ball = np.sqrt(x**2 + y**2 + z**2) - 6.0
    plate = np.maximum.reduce([np.abs(z - 0.1) - half, np.abs(y) - 5.0, x - 12.0, -x])
    raw = mesh_from_field(np.clip(0.5 - np.minimum(ball, plate), 0.0, 1.0).astype(np.float32), grid)
    v = raw.vertices
    on_plate = (v[:, 0] > 7.5) & (v[:, 0] < 11.5) & (np.abs(v[:, 1]) < 4.0)
    on_ball = (np.linalg.norm(v, axis=1) < 6.5) & (np.abs(v[:, 2]) > 3.0)
    return raw, on_plate, on_ball


def test_thin_vertices_finds_the_parts_thinner_than_twice_the_depth():
    """A plate 0.6 mm thick (1 mm voxels, coverage field) on a 6 mm ball: the plate's vertices away from the ball are
    thin, the ball's away from the plate are not (a probe half a voxel deep stays inside it)."""
    from organlab.surface._deviation import _surface
    from organlab.surface._thin import thin_vertices

    raw, on_plate, on_ball = _plate_on_ball(0.3)
    v = raw.vertices
    thin = thin_vertices(_surface(raw), 0.5)
    assert on_plate.sum() > 30 and on_ball.sum() > 100
    # measured: every flat-plate vertex thin, no ball vertex
    assert thin[on_plate].all()
    assert not thin[on_ball].any()
    # a probe deeper than the plate's thickness is needed: a tenth of a voxel finds nothing on the plate either
    assert not thin_vertices(_surface(raw), 0.1)[on_plate].any()


def _as_band(field, grid, block=8):
    """``field`` (float32) as a :class:`BandField` whose every block is a band block (meshed chunk by chunk)."""
    from organlab.bandfield import BandField

    nb = [-(-s // block) for s in field.shape]
    full = np.full([b * block for b in nb], -0.5, dtype=np.float32)
    full[: field.shape[0], : field.shape[1], : field.shape[2]] = field
    values = full.reshape(nb[0], block, nb[1], block, nb[2], block).transpose(0, 2, 4, 1, 3, 5)
    values = values.reshape(-1, block, block, block)
    return BandField(grid, block, np.full(nb, 2, dtype=np.int8), np.arange(np.prod(nb), dtype=np.int32).reshape(nb),
                     np.ascontiguousarray(values))


# Samples exactly at the level (._bandmesh.untie): Lewiner's marching cubes put every vertex of the edges from such a
# sample on it, dropped the triangles of those coincident vertices and left holes.  Measured before -> after:
#   fins coverage 0.9 seed 0 (145 samples at 0.5)  5 holes, 18 boundary edges, finished by the open-surface path
#       3.46 voxels off, 8.3 deg  ->  closed; 0.417 / 0.034 voxel, 21.4 deg, the adaptive path, no last step
#   fins coverage 1.0 seed 7 (not looked at before the fix)  6 boundary edges, the open-surface path, 2.24 voxels
#       off, 20.1 deg  ->  closed; 0.387 / 0.027 voxel, 21.3 deg
# (the ~145 samples at 0.5 are the ball's: grid points at exactly 15 mm from its centre; 11 of 48 scenes of fins
# 0.4-1.2 voxel thick, seeds 3-8, had holes.)
@pytest.mark.parametrize("scene", [(0.9, 0), (1.0, 7)])
def test_samples_exactly_at_the_level_leave_no_hole(scene):
    from organlab.surface._quality import mesh_quality
    from organlab.surface._repair import repair_mesh

    field, grid = finned_ball("coverage", *scene)
    assert (field == 0.5).sum() > 100  # the case is real
    dense, band = mesh_from_field(field, grid), mesh_from_field(_as_band(field, grid), grid)
    for m in (dense, band):
        q = mesh_quality(m)
        assert q["boundary_edges"] == q["nonmanifold_edges"] == q["nonmanifold_vertices"] == 0, q
    # the chunked surface is the dense one (float32 rounding of the vertices only: volumes 1.3e-8 and 1.7e-8 apart,
    # 1.5e-8 before the fix)
    assert len(band.faces) == len(dense.faces) and abs(band.volume / dense.volume - 1) < 1e-7
    fin = finish_surface(dense, voxel_size=1.0)
    names = [s["step"] for s in fin.steps]
    assert "folds" not in names and "stay_on_data" not in names, names  # the closed surface's path
    dev = surface_deviation(fin.mesh, repair_mesh(dense, speck_mm=3.0)[0], voxel_size=1.0)
    assert dev["max_voxels"] < 1.0 and dev["mean_voxels"] < 0.25, dev
    assert fin.watertight and fin.final["min_angle_deg"] >= 20.0


def test_thickened_gives_a_part_thinner_than_a_voxel_its_thickness():
    """A plate 0.3 mm thick (1 mm voxels, coverage field) on a 6 mm ball: marching cubes gives its middle as two sheets
    0.02-0.38 mm apart; thickened to 0.6 mm, each sheet moves out, the ball stays where it is."""
    from organlab.surface._thin import thickened

    raw, on_plate, on_ball = _plate_on_ball(0.15)
    v = raw.vertices
    out, n = thickened(raw, 0.5, 0.6)
    assert on_plate.sum() > 30 and on_ball.sum() > 100 and np.array_equal(out.faces, raw.faces)
    assert np.abs(v[on_plate, 2] - 0.1).min() < 0.05  # the case is real: the sheets nearly touch (0.009 mm)
    # measured: every plate vertex at least 0.199 mm from the middle plane (0.4 mm apart), none of the ball's moved,
    # no vertex more than 0.373 mm (bound 0.4: the promise's budget is a voxel); 110 vertices moved
    assert np.abs(out.vertices[on_plate, 2] - 0.1).min() > 0.19
    assert np.array_equal(out.vertices[on_ball], v[on_ball])
    assert 0 < n < len(v) and np.linalg.norm(out.vertices - v, axis=1).max() < 0.4
    assert out.volume > raw.volume
    # a part already thicker is left alone: the ball alone is returned as it is
    grid = VoxelGrid(origin=(-14.0,) * 3, voxel_size=1.0, shape=(29, 29, 29))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    alone = mesh_from_field(np.clip(6.5 - np.sqrt(x**2 + y**2 + z**2), 0.0, 1.0).astype(np.float32), grid)
    assert thickened(alone, 0.5, 0.6) == (alone, 0)


# Scenes rendered after ._thin.thickened's thickness and rounds were fixed (seeds 9-11; the rule was chosen on seeds
# 0-8).  Before (the raw lace remeshed as it was) -> now, max / mean voxels, smallest angle:
#   fins coverage 0.42 seed 11   8.317 / 0.376, 22.4 deg (sliver cut and last step)  ->  0.518 / 0.087, 21.4 deg
#   fins coverage 0.3 seed 10    4.349 / 0.159, 20.9 deg (sliver cut and last step)  ->  0.503 / 0.070, 21.3 deg
# (the 9 scenes 0.3 / 0.42 / 0.65 voxel thick, seeds 9-11: 0.65-8.94 voxels, 6 of 9 over 1, -> 0.36-0.93, 20.0-22.1 deg)
# Bounds: the promises, reached by the remesher alone (no sliver cut, no last step: measured none ran).
@pytest.mark.parametrize("thick, seed", [(0.42, 11), (0.3, 10)])
def test_parts_under_half_a_voxel_keep_their_shape(thick, seed):
    from organlab.surface._repair import repair_mesh

    raw = mesh_from_field(*finned_ball("coverage", thick, seed))
    fin = finish_surface(raw, voxel_size=1.0)
    names = [s["step"] for s in fin.steps]
    thin = [s for s in fin.steps if s["step"] == "thin"]
    assert thin and thin[0]["vertices_thickened"] > 100, names  # the case is real: parts under 0.6 voxel
    assert "stay_on_data" not in names and "slivers" not in names, names
    dev = surface_deviation(fin.mesh, repair_mesh(raw, speck_mm=3.0)[0], voxel_size=1.0)
    assert dev["max_voxels"] < 1.0 and dev["mean_voxels"] < 0.25, dev
    assert fin.watertight and fin.final["min_angle_deg"] >= 20.0, fin.final["min_angle_deg"]
    assert fin.final["nonmanifold_edges"] == 0 and fin.final["boundary_edges"] == 0
