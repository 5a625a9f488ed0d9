import numpy as np
import pytest

from organlab.grid import VoxelGrid
from organlab.surface import Mesh, mesh_from_volume, read_ply, write_ply, write_stl


def _sphere_field(grid, center, radius):
    """0.5 + signed distance / voxel: its 0.5 level is the sphere."""
    c = grid.centers().reshape(*grid.shape, 3)
    d = radius - np.linalg.norm(c - center, axis=-1)
    # clip beyond +-1 voxel only: marching cubes interpolates linearly along voxel edges,
    # so both samples of an edge that crosses the surface must keep their true values
    return np.clip(0.5 + d / grid.voxel_size, -1, 2)


@pytest.mark.parametrize("voxel", [1.0, 2.0])
def test_field_surface_volume_and_area(voxel):
    r = 20.0
    grid = VoxelGrid.from_roi([-25, -25, -25], [25, 25, 25], voxel)
    mesh = mesh_from_volume(_sphere_field(grid, np.zeros(3), r), grid)
    assert mesh.is_watertight
    # flat facets lie inside the curved surface: chord error grows with the voxel size
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * r**3, rel=0.004 * voxel)
    assert mesh.area == pytest.approx(4 * np.pi * r**2, rel=0.01)
    # vertices lie on the sphere in world coordinates
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - r).max() < 0.05 * voxel


def test_occupancy_touching_roi_closes_and_is_in_world_frame():
    # a box filling the grid entirely: padding must close it; world position must be right
    grid = VoxelGrid.from_roi([10, 20, 0], [20, 26, 8], 1.0)
    occ = np.ones(grid.shape, bool)
    mesh = mesh_from_volume(occ, grid)
    assert mesh.is_watertight and mesh.volume > 0
    lo, hi = mesh.bounds
    # the 0.5 level between the last voxel centre and the padding lies on the roi faces
    np.testing.assert_allclose(lo, [10, 20, 0], atol=1e-9)
    np.testing.assert_allclose(hi, [20, 26, 8], atol=1e-9)
    # faces oriented outward: the normals of the top faces point up
    v = mesh.vertices[mesh.faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    top = np.all(np.isclose(v[:, :, 2], 8.0), axis=1)
    assert top.any() and (n[top, 2] > 0).all()


def test_two_components_and_no_degenerate_faces():
    grid = VoxelGrid.from_roi([0, 0, 0], [30, 10, 10], 1.0)
    occ = np.zeros(grid.shape, bool)
    occ[2:8, 2:8, 2:8] = True
    occ[15:25, 2:8, 2:8] = True
    mesh = mesh_from_volume(occ, grid)
    assert mesh.is_watertight
    v = mesh.vertices[mesh.faces]
    area = np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    assert area.min() > 1e-9
    # marching cubes cuts the corners of a voxel box: volume a little under the voxel count
    assert 0.8 * grid.volume_of(occ) < mesh.volume < grid.volume_of(occ)


def test_watertight_detects_holes_and_flips():
    grid = VoxelGrid.from_roi([-12, -12, -12], [12, 12, 12], 1.0)
    mesh = mesh_from_volume(_sphere_field(grid, np.zeros(3), 10), grid)
    holed = Mesh(mesh.vertices, mesh.faces[1:])
    assert not holed.is_watertight and holed.edge_counts()[0] == 3
    f = mesh.faces.copy()
    f[0] = f[0, ::-1]
    assert not Mesh(mesh.vertices, f).is_watertight


def test_empty_volume_raises():
    grid = VoxelGrid.from_roi([0, 0, 0], [5, 5, 5], 1.0)
    with pytest.raises(ValueError, match="empty"):
        mesh_from_volume(np.zeros(grid.shape, bool), grid)
    with pytest.raises(ValueError, match="does not match"):
        mesh_from_volume(np.zeros((2, 2, 2), bool), grid)


def test_ply_and_stl_roundtrip(tmp_path):
    grid = VoxelGrid.from_roi([-12, -12, -12], [12, 12, 12], 1.0)
    mesh = mesh_from_volume(_sphere_field(grid, np.zeros(3), 10), grid)
    colors = (np.abs(mesh.vertices) * 20).clip(0, 255).astype(np.uint8)
    colored = Mesh(mesh.vertices, mesh.faces, colors)
    write_ply(tmp_path / "m.ply", colored)
    back = read_ply(tmp_path / "m.ply")
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-4)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_array_equal(back.vertex_colors, colors)
    assert back.volume == pytest.approx(mesh.volume, rel=1e-5)
    write_stl(tmp_path / "m.stl", mesh)
    data = (tmp_path / "m.stl").read_bytes()
    n = int(np.frombuffer(data[80:84], "<u4")[0])
    assert n == len(mesh.faces) and len(data) == 84 + 50 * n
    rec = np.frombuffer(data[84:], dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")])
    np.testing.assert_allclose(rec["v"], mesh.vertices[mesh.faces], atol=1e-4)
    # stored normals point outward on a sphere centred at the origin
    assert ((rec["n"] * rec["v"].mean(axis=1)).sum(axis=1) > 0).all()
