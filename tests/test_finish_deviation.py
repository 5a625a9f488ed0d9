"""Issue 21 part 2: finish_surface states how far the finished surface lies from the raw one.

The figures are checked against a brute-force closest point (every face of the other surface), and
on a specimen the defaults never saw: a ball (radius 12 mm) with a fin thinner than the remesh edge
(1.2 mm thick, 1 mm voxels, 1.5 mm edges).  Measured (this session): the ball alone stays on
its raw surface (mean 0.022, max 0.098 voxel, 27.9 degrees); with the fin, the finished surface
loses most of it (raw to finished: mean 0.57, max 8.7 voxels; 29.7 degrees), and the figures say so.
The issue's bound (mean 0.25, max 1 voxel) is NOT met on such a fin yet: fold cutting and remeshing
at one edge length for the whole model remove it.
"""

import numpy as np
import pytest

from organlab.grid import VoxelGrid
from organlab.surface import FinishedSurface, closest_points, finish_surface, mesh_from_field, surface_deviation
from organlab.surface._deviation import _tri_closest


def _field(fin):
    grid = VoxelGrid(origin=(-20.0, -20.0, -20.0), voxel_size=1.0, shape=(41, 41, 41))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    d = np.sqrt(x**2 + y**2 + z**2) - 12.0  # signed distance to the ball, mm
    if fin:  # a plate 1.2 mm thick, 16 mm wide, out to x = 18 mm
        plate = np.maximum.reduce([np.abs(z) - 0.6, np.abs(y) - 8.0, x - 18.0, -x])
        d = np.minimum(d, plate)
    return np.clip(0.5 - d, 0.0, 1.0).astype(np.float32), grid  # a coverage-like field, its 0.5 level at d = 0


def _brute(points, mesh):
    v, f = mesh.vertices, mesh.faces
    return np.array([np.sqrt(((_tri_closest(np.repeat(p[None], len(f), 0), v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]) - p) ** 2)
                             .sum(1)).min() for p in points])


def test_closest_points_match_a_brute_force_search():
    field, grid = _field(True)
    raw = mesh_from_field(field, grid)
    rng = np.random.default_rng(1)
    p = raw.vertices[rng.integers(0, len(raw.vertices), 200)] + rng.normal(0.0, 0.4, (200, 3))
    _, d = closest_points(p, raw)
    b = _brute(p, raw)
    # never nearer than the true nearest point; among 6 candidate triangles by centroid, a few points by
    # the fin's small marching-cubes triangles get a farther one (measured: 0.0041 mm at most, a few of 200)
    assert np.all(d >= b - 1e-9)
    np.testing.assert_allclose(d, b, atol=0.01)
    assert np.mean(np.abs(d - b) < 1e-9) > 0.9


@pytest.fixture(scope="module")
def finished():
    out = {}
    for fin in (False, True):
        field, grid = _field(fin)
        raw = mesh_from_field(field, grid)
        out[fin] = raw, finish_surface(raw, voxel_size=1.0)
    return out


def test_finish_surface_is_typed_and_reports_its_deviation(finished):
    raw, res = finished[False]
    assert isinstance(res, FinishedSurface)
    d = res.to_dict()
    assert set(d) >= {"steps", "raw", "final", "watertight", "volume_change_pct", "deviation"}
    mesh, report = res  # the former (Mesh, dict) form
    assert mesh is res.mesh and report == d
    # the figures are what an independent search gives (finished vertices to the raw surface)
    sub = res.mesh.vertices[::25]
    brute = _brute(sub, raw)
    assert res.deviation["finished_to_raw"]["max_voxels"] >= brute.max() - 1e-6
    assert res.deviation == surface_deviation(res.mesh, raw, voxel_size=1.0)
    # a smooth ball stays on its raw surface: measured mean 0.022, max 0.098 voxel
    assert res.deviation["mean_voxels"] < 0.25 and res.deviation["max_voxels"] < 1.0
    assert res.watertight and res.final["min_angle_deg"] >= 20.0


def test_a_fin_thinner_than_the_remesh_edge_shows_in_the_deviation(finished):
    raw_ball, ball = finished[False]
    raw, res = finished[True]
    assert res.watertight and res.final["min_angle_deg"] >= 20.0  # the FEA promises hold
    # the raw fin's rim: raw vertices beyond the ball, how far the finished surface is from them
    _, d = closest_points(raw.vertices, res.mesh)
    rim = np.linalg.norm(raw.vertices, axis=1) > 14.0
    assert res.deviation["raw_to_finished"]["max_voxels"] == pytest.approx(d.max(), abs=1e-3)
    # the fin is where the surface departs most: its worst point is on the fin, and worse than the ball's
    assert d[rim].max() == pytest.approx(d.max())
    assert res.deviation["max_voxels"] > ball.deviation["max_voxels"]


def test_the_report_states_the_deviation_and_the_worst_view_iou_change(small_session):
    from organlab.pipeline import reconstruct

    rec = reconstruct(small_session, voxel_size=2.0)
    dev = rec.report["surface"]["deviation"]
    rows = [v["agreement"] for v in rec.report["views"]]
    change = [r["iou"] - r["raw_iou"] for r in rows]
    k = int(np.argmax(np.abs(change)))
    assert dev["worst_view_iou_change"] == pytest.approx(change[k], abs=1e-5)
    assert dev["worst_view"] == rec.report["views"][k]["image"]
    # the raw IoU is the raw mesh's own: re-rendered here
    from organlab.raster import model_mask

    cam, sil = rec.cameras[k], np.asarray(rec.silhouettes[k].coverage) >= 0.5
    r = model_mask(rec.raw_mesh, cam, sil.shape)
    assert rows[k]["raw_iou"] == pytest.approx((r & sil).sum() / (r | sil).sum(), abs=1e-9)
    # 6 views of the sample at 2 mm: measured mean 0.064, max 1.99 voxels, worst view IoU change -0.0089
    # (views/120.jpg): at 2 mm the 3 mm remesh edge rounds the neck off (the 0.002 bound is not met)
    assert 0 < dev["mean_voxels"] < 0.25 and -0.02 < dev["worst_view_iou_change"] < 0
