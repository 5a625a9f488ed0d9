"""Surface: marching cubes, repair and remeshing, measurements and exports.

Public names are re-exported from private modules by topic:

- :mod:`._mesh`: the :class:`Mesh` type, :func:`mesh_from_volume` (Lewiner
  marching cubes, or the teaching classic one of :mod:`._classic_mc`);
- :mod:`._io`: PLY, STL, OBJ, VTK/VTU files;
- :mod:`._quality`, :mod:`._repair`: triangle quality, pymeshlab repair,
  smoothing, isotropic remeshing, :func:`finish_surface` (a :class:`FinishedSurface`),
  :func:`warm_kernels` (its kernels loaded ahead of its first call);
- :mod:`._deviation`: closest points on a mesh, a finished surface's deviation from the raw one;
- :mod:`._voronoi`: crust reconstruction from points, screened Poisson;
- :mod:`._aaa`: centreline and aneurysm measurements;
- :mod:`._tetra`: tetrahedral meshes (gmsh) and their files (meshio);
- :mod:`._result`: the ``organlab mesh`` steps on a result folder;
- :mod:`._picture`: off-screen pictures of a mesh and of the AAA measures.
"""

from ._aaa import AAAMeasures, measure_aaa
from ._deviation import closest_points, surface_deviation
from ._io import read_obj, read_ply, write_obj, write_ply, write_stl, write_vtk
from ._mesh import MC_METHODS, Mesh, MeshMeasures, color_vertices, measure, mesh_from_field, mesh_from_volume
from ._picture import aaa_picture, mesh_snapshot
from ._quality import boundary_loops, mesh_quality
from ._repair import FinishedSurface, finish_surface, release_heap, remesh_mesh, repair_mesh, smooth_mesh, warm_kernels
from ._result import is_aaa_session, load_voxels, mesh_result
from ._tetra import TETRA_FORMATS, TetMesh, read_tetra, tet_quality, tetrahedralize, write_tetra
from ._voronoi import crust, labelled_balls, poisson_surface, poles, vertex_normals

__all__ = [
    "Mesh",
    "mesh_from_volume",
    "mesh_from_field",
    "measure",
    "MeshMeasures",
    "color_vertices",
    "MC_METHODS",
    "write_ply",
    "write_stl",
    "read_ply",
    "write_obj",
    "read_obj",
    "write_vtk",
    "mesh_quality",
    "boundary_loops",
    "finish_surface",
    "warm_kernels",
    "release_heap",
    "FinishedSurface",
    "surface_deviation",
    "closest_points",
    "repair_mesh",
    "smooth_mesh",
    "remesh_mesh",
    "measure_aaa",
    "AAAMeasures",
    "tetrahedralize",
    "TetMesh",
    "tet_quality",
    "write_tetra",
    "read_tetra",
    "TETRA_FORMATS",
    "crust",
    "labelled_balls",
    "poles",
    "poisson_surface",
    "vertex_normals",
    "mesh_result",
    "load_voxels",
    "is_aaa_session",
    "aaa_picture",
    "mesh_snapshot",
]
