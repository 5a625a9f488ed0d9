"""Surface: marching cubes, repair and remeshing, measurements and exports.

Public names are re-exported from private modules by topic:

- :mod:`._mesh`: the :class:`Mesh` type, :func:`mesh_from_volume` (Lewiner
  marching cubes, or the teaching classic one of :mod:`._classic_mc`);
- :mod:`._io`: PLY, STL, OBJ, VTK/VTU files;
- :mod:`._quality`, :mod:`._repair`: triangle quality, pymeshlab repair,
  smoothing, isotropic remeshing, :func:`finish_surface`;
- :mod:`._voronoi`: crust reconstruction from points, screened Poisson;
- :mod:`._aaa`: centreline and aneurysm measurements;
- :mod:`._tetra`: tetrahedral meshes (gmsh) and their files (meshio);
- :mod:`._truth`: distance to a synthetic specimen's exact surface.
"""

from ._io import read_ply, write_ply, write_stl
from ._mesh import MC_METHODS, Mesh, mesh_from_volume
from ._quality import boundary_loops, mesh_quality
from ._repair import finish_surface, remesh_mesh, repair_mesh, smooth_mesh
from ._truth import distance_to_specimen, surface_samples

__all__ = [
    "Mesh",
    "mesh_from_volume",
    "MC_METHODS",
    "write_ply",
    "write_stl",
    "read_ply",
    "mesh_quality",
    "boundary_loops",
    "finish_surface",
    "repair_mesh",
    "smooth_mesh",
    "remesh_mesh",
    "distance_to_specimen",
    "surface_samples",
]
