"""Off-screen pictures of a surface (pyvista, EGL): the mesh, and the AAA measures on it.

pyvista is imported inside the functions (a heavy optional library), so
``import organlab`` stays fast.  Off-screen rendering goes through EGL: no X
server is needed.  Re-exported by :mod:`organlab.figures`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..mesh import Mesh
from ._aaa import AAAMeasures

__all__ = ["mesh_snapshot", "aaa_picture"]


def mesh_snapshot(mesh: Mesh, path: str | Path, *, window_size: tuple[int, int] = (800, 600), title: str | None = None,
                  elevation_deg: float = 20.0, azimuth_deg: float = -60.0) -> Path:
    """Render a mesh off-screen to a PNG.

    Parameters
    ----------
    mesh : organlab.surface.Mesh
        World frame, mm (Z up).
    path : str or Path
        PNG to write.
    window_size : (2,) int
        ``(width, height)`` px.
    title : str, optional
        Text drawn in the upper-left corner.
    elevation_deg, azimuth_deg : float
        Viewing direction, degrees (azimuth from +X about +Z, elevation above
        the XY plane).

    Returns
    -------
    Path
    """
    p, poly = _plotter(mesh, window_size)
    if mesh.vertex_colors is not None:
        poly.point_data["rgb"] = np.asarray(mesh.vertex_colors, dtype=np.uint8)
        p.add_mesh(poly, scalars="rgb", rgb=True, smooth_shading=True)
    else:
        p.add_mesh(poly, color="#d98c7a", smooth_shading=True, specular=0.2)
    p.show_grid(xtitle="x (mm)", ytitle="y (mm)", ztitle="z (mm)", font_size=8)
    if title:  # a line of its own above the scene, 10 px from the top and left edges
        p.add_text(title, position=(10, window_size[1] - 28), font_size=10, color="black")
    # the grid's tick labels and titles lie outside the mesh's bounds: 1.6 x its bounding sphere keeps them and
    # the title inside the picture (1.15 clipped the x title at the bottom and ran the top labels into the title)
    return _shoot(p, mesh, path, elevation_deg, azimuth_deg, 1.6)


def aaa_picture(mesh: Mesh, measures: AAAMeasures, path: str | Path, *, window_size: tuple[int, int] = (900, 900)) -> Path:
    """The mesh (translucent) with its centreline and the maximum-diameter section, off-screen (pyvista, EGL).

    Parameters
    ----------
    mesh : organlab.surface.Mesh
        World frame, mm.
    measures : organlab.surface.AAAMeasures
    path : str or Path
        PNG to write.
    window_size : (2,) int
        ``(width, height)`` px.

    Returns
    -------
    Path
    """
    import pyvista as pv

    p, poly = _plotter(mesh, window_size)
    p.add_mesh(poly, color="#d98c7a", opacity=0.35, smooth_shading=True)
    p.add_mesh(pv.lines_from_points(measures.centreline), color="#1f4e9c", line_width=5)
    sec = np.vstack([measures.max_section, measures.max_section[:1]])
    p.add_mesh(pv.lines_from_points(sec), color="#c0102a", line_width=6)
    p.add_mesh(pv.PolyData(measures.max_location_mm[None]), color="#c0102a", point_size=14, render_points_as_spheres=True)
    s = measures.summary()
    p.add_text(
        f"max diameter {s['max_diameter_mm']:.1f} mm (equivalent {s['max_equivalent_diameter_mm']:.1f} mm)\n"
        f"at z = {s['max_location_mm'][2]:.1f} mm, {s['max_arc_mm']:.0f} mm along the centreline\n"
        f"neck {s['neck_diameter_mm']:.1f} mm, sac {s['sac_length_mm']:.0f} mm long, {s['sac_volume_mm3'] / 1000:.1f} cm3",
        position="upper_left", font_size=11, color="black",
    )
    return _shoot(p, mesh, path, 22.0, -70.0, 1.1)


def _plotter(mesh, window_size):
    """An off-screen pyvista plotter on white, and the mesh as PolyData."""
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    faces = np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).ravel()
    poly = pv.PolyData(np.asarray(mesh.vertices, dtype=np.float64), faces)
    p = pv.Plotter(off_screen=True, window_size=tuple(window_size))
    p.set_background("white")
    return p, poly


def _shoot(p, mesh, path, elevation_deg, azimuth_deg, margin):
    """Aim at the mesh from a direction (degrees) and write the PNG."""
    lo, hi = mesh.bounds
    center = (lo + hi) / 2
    # far enough that the bounding sphere (times margin) fits in pyvista's 30-degree vertical view angle
    dist = margin * float(np.linalg.norm(hi - lo)) / 2 / np.tan(np.deg2rad(15.0))
    el, az = np.deg2rad(elevation_deg), np.deg2rad(azimuth_deg)
    eye = center + dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    p.camera_position = [tuple(eye), tuple(center), (0, 0, 1)]
    path = Path(path)
    p.screenshot(str(path))
    p.close()
    return path
