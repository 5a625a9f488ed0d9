"""Issue 21: the finished surface stays within 1 voxel of the raw one (``finish_surface``'s ``deviation``).

A ball with thin fins (half a voxel to a voxel thick) at coarse voxels: the remesher's sliver clean-up flattens
the fins' knife edges (faces folded back by more than 150 degrees, where no triangle of 20 degrees fits) and cuts
out and fills what it still cannot fix, shaving the fins' tips by up to 3.5 voxels.  The last step
(``stay_on_data``, :mod:`organlab.surface._guard`) puts the lost raw points back as vertices and pulls the
vertices still more than 0.9 voxel off back onto the raw surface, keeping the smallest angle.
"""

import numpy as np
import pytest

import organlab as ol
from organlab.surface._deviation import surface_deviation
from organlab.surface._repair import repair_mesh


def _finned_ball(voxel_size, seed):
    """A 15 mm ball with three half-discs of radius 24 mm, 1-2 voxels thick (random planes), and its grid."""
    n = int(60 / voxel_size) + 1
    grid = ol.VoxelGrid(origin=(-30.0,) * 3, voxel_size=voxel_size, shape=(n, n, n))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    body = x**2 + y**2 + z**2 <= 15.0**2
    rng = np.random.default_rng(seed)
    for _ in range(3):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        e = np.cross(d, rng.normal(size=3))
        e /= np.linalg.norm(e)
        body |= ((np.abs(x * d[0] + y * d[1] + z * d[2]) <= rng.uniform(0.5, 1.0) * voxel_size)
                 & (x**2 + y**2 + z**2 <= 24.0**2) & (x * e[0] + y * e[1] + z * e[2] > 0))
    return ol.mesh_from_field(body, grid)


# measured (before -> after the last step): seed 0 at 2 mm 3.4555 -> 0.8392 voxels, seed 1 at 1.5 mm (a
# scene the step was not developed on) 1.0157 -> 0.7197; the smallest angles 20.23 and 20.48 degrees
@pytest.mark.parametrize("voxel_size, seed", [(2.0, 0), (1.5, 1)])
def test_finished_fins_stay_within_a_voxel(voxel_size, seed):
    raw = _finned_ball(voxel_size, seed)
    fin = ol.finish_surface(raw, voxel_size=voxel_size)
    guard = [s for s in fin.steps if s["step"] == "stay_on_data"]
    # the case is real: without the last step the finished surface was more than a voxel off the raw one
    assert len(guard) == 1 and guard[0]["max_voxels"][0] > 1.0, fin.steps
    assert guard[0]["vertices_inserted"] > 0
    # the promise, measured again here independently of the report (against the raw surface less its specks)
    repaired, _ = repair_mesh(raw, speck_mm=3.0 * voxel_size)
    dev = surface_deviation(fin.mesh, repaired, voxel_size=voxel_size)
    assert dev["max_voxels"] < 1.0 and dev["mean_voxels"] < 0.25, dev
    assert dev == {k: fin.deviation[k] for k in dev}
    # the FEA promises still hold
    assert fin.watertight and fin.mesh.is_watertight
    assert fin.final["min_angle_deg"] >= 20.0
    assert fin.final["nonmanifold_edges"] == 0 and fin.final["boundary_edges"] == 0
    # the volume is the raw's (the whole finishing: measured -0.30 % and +0.03 %; the fins are a few voxels thin)
    assert abs(fin.volume_change_pct) < 0.5, fin.volume_change_pct


def test_within_a_voxel_already_is_left_alone():
    """A plain ball (1.5 mm voxels) is within a voxel after remeshing: no last step, the same surface."""
    grid = ol.VoxelGrid(origin=(-24.0,) * 3, voxel_size=1.5, shape=(33, 33, 33))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    fin = ol.finish_surface(ol.mesh_from_field(x**2 + y**2 + z**2 <= 20.0**2, grid), voxel_size=1.5)
    assert fin.deviation["max_voxels"] < 1.0
    assert not [s for s in fin.steps if s["step"] == "stay_on_data"]
