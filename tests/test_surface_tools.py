"""Teaching marching cubes, repair, measurements and point reconstructions on
analytic shapes the defaults were never tuned on (a noisy sphere, a tilted
bulging tube, a random field)."""

import numpy as np
import pytest
from scipy import ndimage

from organlab.grid import VoxelGrid
from organlab.surface import (
    Mesh,
    boundary_loops,
    finish_surface,
    labelled_balls,
    measure_aaa,
    mesh_from_volume,
    mesh_quality,
    read_obj,
    vertex_normals,
    write_obj,
    write_vtk,
)
from organlab.synthetic import Sphere, distance_to_specimen


def _random_field(seed, n=20):
    """A smooth random field: its zero level is full of ambiguous faces."""
    f = ndimage.gaussian_filter(np.random.default_rng(seed).standard_normal((n, n, n)), 1.5)
    return f / f.std()


@pytest.mark.parametrize("seed", [1, 2])
def test_classic_marching_cubes_opens_holes_the_decider_closes(seed):
    grid = VoxelGrid.from_roi([0, 0, 0], [20, 20, 20], 1.0)
    f = _random_field(seed)
    lewiner = mesh_from_volume(f, grid, level=0.0)
    decider = mesh_from_volume(f, grid, level=0.0, method="decider")
    classic = mesh_from_volume(f, grid, level=0.0, method="classic")
    # measured: seed 1 -> 64 boundary edges in 3+ holes; the other two closed and consistently oriented
    assert classic.edge_counts()[0] > 0 and len(boundary_loops(classic)) > 0
    assert lewiner.is_watertight and decider.is_watertight
    assert mesh_quality(decider)["nonmanifold_vertices"] == 0
    # same surface: the decider's volume agrees with Lewiner's (measured 0.05 %)
    assert decider.volume == pytest.approx(lewiner.volume, rel=0.005)


def _sphere_field(grid, radius, noise=0.0, seed=0):
    c = grid.centers().reshape(*grid.shape, 3)
    f = 0.5 + (radius - np.linalg.norm(c, axis=-1)) / grid.voxel_size
    if noise:
        n = ndimage.gaussian_filter(np.random.default_rng(seed).standard_normal(grid.shape), 1.0)
        f = f + noise * n / n.std()
    return np.clip(f, -1, 2)


def test_decider_surface_lies_on_a_sphere():
    grid = VoxelGrid.from_roi([-26, -26, -26], [26, 26, 26], 1.0)
    mesh = mesh_from_volume(_sphere_field(grid, 20.0), grid, method="decider")
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * 20.0**3, rel=0.004)
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 20.0).max() < 0.05


def test_finish_surface_repairs_a_holed_noisy_sphere():
    # classic marching cubes of a noisy sphere: holes at ambiguous faces (measured: 12 edges in 3 holes)
    grid = VoxelGrid.from_roi([-26, -26, -26], [26, 26, 26], 1.0)
    raw = mesh_from_volume(_sphere_field(grid, 20.0, noise=0.35, seed=3), grid, method="classic")
    assert raw.edge_counts()[0] > 0
    out, report = finish_surface(raw, voxel_size=1.0)
    q = report["final"]
    assert out.is_watertight and report["watertight"]
    assert q["nonmanifold_edges"] == q["nonmanifold_vertices"] == q["boundary_edges"] == 0
    assert report["steps"][0]["holes_closed"] == len(boundary_loops(raw))
    assert q["min_angle_deg"] >= 20.0  # measured 29.7
    assert report["raw"]["min_angle_deg"] < 5.0  # the marching-cubes slivers are gone
    # the noise moves the surface by about 0.35 voxel; the finished surface stays on the raw one (issue 21), noise
    # included: measured 0.267 mm from the sphere against the raw's 0.256 (before issue 21 the Taubin-smoothed
    # surface was remeshed, 0.22 mm, but that also shaved thin parts off real specimens)
    d_raw = np.abs(distance_to_specimen(raw.vertices, Sphere((0, 0, 0), 20.0))).mean()
    d_out = np.abs(distance_to_specimen(out.vertices, Sphere((0, 0, 0), 20.0))).mean()
    assert d_out < 1.1 * d_raw
    assert report["deviation"]["mean_voxels"] < 0.25 and report["deviation"]["max_voxels"] < 1.0  # measured 0.043 / 0.25
    assert out.volume == pytest.approx(4 / 3 * np.pi * 20.0**3, rel=0.01)


def _tube(tilt_deg=30.0, r0=8.0, bulge=12.0, s_max=70.0, width=15.0):
    """A straight tube tilted from Z with a Gaussian bulge: field, grid, axis point/direction, radius(s)."""
    grid = VoxelGrid.from_roi([-50, -50, 0], [50, 50, 120], 1.0)
    c = grid.centers().reshape(*grid.shape, 3)
    a = np.array([np.sin(np.radians(tilt_deg)), 0.0, np.cos(np.radians(tilt_deg))])
    p0 = np.array([-60.0 * a[0] / a[2], 0.0, 0.0])

    def radius(s):
        return r0 + bulge * np.exp(-(((s - s_max) / width) ** 2))

    q = c - p0
    s = q @ a
    perp = np.linalg.norm(q - s[..., None] * a, axis=-1)
    return np.clip(0.5 + (radius(s) - perp), -1, 2), grid, p0, a, radius


def test_measure_aaa_on_a_tilted_bulging_tube():
    f, grid, p0, a, radius = _tube()
    m = measure_aaa(f, grid)
    # perpendicular sections: the bulge's circle of diameter 40 mm (a horizontal cut would give 46 mm)
    assert abs(m.max_diameter_mm - 40.0) < 1.0  # measured 39.98
    assert abs(m.max_equivalent_mm - 40.0) < 1.0
    assert np.linalg.norm(m.max_location_mm - (p0 + 70.0 * a)) < 5.0  # measured 0.6 mm
    assert abs(m.neck_diameter_mm - 16.0) < 1.0  # measured 15.97
    # sac: radius > 1.2 * 8 mm <=> |s - 70| < 15 sqrt(ln(12 / 1.6))
    half = 15.0 * np.sqrt(np.log(12.0 / 1.6))
    assert abs(m.sac_length_mm - 2 * half) < 2.0  # measured 42.66 against 42.61
    s = np.linspace(70 - half, 70 + half, 2001)
    exact = np.trapezoid(np.pi * radius(s) ** 2, s)
    assert m.sac_volume_mm3 == pytest.approx(exact, rel=0.03)
    # the centreline keeps to the axis
    q = m.centreline - p0
    off = np.linalg.norm(q - np.outer(q @ a, a), axis=1)
    assert np.median(off) < 1.0


def test_measure_aaa_rejects_an_empty_model():
    from organlab.errors import OrganlabError

    grid = VoxelGrid.from_roi([0, 0, 0], [10, 10, 10], 1.0)
    with pytest.raises(OrganlabError, match="empty"):
        measure_aaa(np.zeros(grid.shape), grid)


@pytest.mark.parametrize("axes", [(22.0, 17.0, 12.0), (21.0, 19.0, 15.0)])
def test_labelled_balls_close_the_marching_cubes_points_of_an_ellipsoid(axes):
    grid = VoxelGrid.from_roi([-26, -26, -26], [26, 26, 26], 1.0)
    c = grid.centers().reshape(*grid.shape, 3)
    f = np.clip(0.5 + (1 - np.sqrt(((c / np.array(axes)) ** 2).sum(-1))) * min(axes), -1, 2)
    mc = mesh_from_volume(f, grid)
    balls = labelled_balls(mc.vertices, vertex_normals(mc))
    # closed and manifold here (not on exactly co-spherical or co-planar samples: see docs/surfaces.md)
    assert balls.is_watertight and mesh_quality(balls)["nonmanifold_vertices"] == 0
    assert balls.volume == pytest.approx(mc.volume, rel=0.001)  # measured 4e-7


def test_obj_and_vtk_files_round_trip(tmp_path):
    import meshio

    grid = VoxelGrid.from_roi([-12, -12, -12], [12, 12, 12], 1.0)
    mesh = mesh_from_volume(_sphere_field(grid, 9.0), grid)
    write_obj(tmp_path / "m.obj", mesh)
    back = read_obj(tmp_path / "m.obj")
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    for ext in ("vtk", "vtu"):
        write_vtk(tmp_path / f"m.{ext}", mesh)
        m = meshio.read(tmp_path / f"m.{ext}")
        got = Mesh(m.points.astype(np.float64), m.cells_dict["triangle"].astype(np.int64))
        assert got.is_watertight and got.volume == pytest.approx(mesh.volume, rel=1e-6)


def test_finish_surface_keeps_a_crevice_and_a_tunnel_at_half_mm_voxels():
    # a ball with a V crevice 10 degrees wide across its top and a 0.9 mm tunnel under a 0.6 mm bridge at its
    # bottom (a handle), at 0.5 mm voxels: the surface folds there (neighbouring faces > 90 degrees apart), as the
    # sample's hull does below 1 mm voxels.  Until issue 21 the folds were cut out and filled (the tunnel closed);
    # the adaptive remeshing keeps both, with edges down to 0.35 voxel there
    grid = VoxelGrid.from_roi([-9, -9, -9], [9, 9, 9], 0.5)
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    ball = 7.0 - np.sqrt(x**2 + y**2 + z**2)
    crevice = np.abs(x) - (z - 3.0) * np.tan(np.radians(5.0))
    tunnel = np.sqrt(x**2 + (z + 6.0) ** 2) - 0.45
    raw = mesh_from_volume(np.minimum(np.minimum(ball, crevice), tunnel), grid, level=0.0)
    assert len(raw.vertices) - len(raw.faces) // 2 == 0  # the raw surface: one piece of genus 1
    out, report = finish_surface(raw, voxel_size=0.5)
    q = report["final"]
    assert out.is_watertight and report["watertight"]
    assert q["nonmanifold_edges"] == q["nonmanifold_vertices"] == 0
    assert q["min_angle_deg"] >= 20.0  # measured 28.1
    # the tunnel is still there (genus 1), and the surface stays on the raw one (measured 0.018 / 0.23 voxel)
    assert len(out.vertices) - len(out.faces) // 2 == 0
    assert report["deviation"]["mean_voxels"] < 0.25 and report["deviation"]["max_voxels"] < 1.0
    assert abs(report["volume_change_pct"]) < 0.1  # measured 0.0 % (the raw volume is restored)
    assert [s["step"] for s in report["steps"]] == ["repair", "smooth", "remesh"]
