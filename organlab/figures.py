"""Pictures of results: an off-screen rendering of a mesh (pyvista, EGL).

pyvista is imported inside the function, so ``import organlab`` stays fast.
Off-screen rendering goes through EGL: no X server is needed.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["mesh_snapshot"]


def mesh_snapshot(mesh, path, *, window_size=(800, 600), title=None, elevation_deg=20.0, azimuth_deg=-60.0):
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
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    faces = np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).ravel()
    poly = pv.PolyData(np.asarray(mesh.vertices, dtype=np.float64), faces)
    p = pv.Plotter(off_screen=True, window_size=tuple(window_size))
    p.set_background("white")
    if mesh.vertex_colors is not None:
        poly.point_data["rgb"] = np.asarray(mesh.vertex_colors, dtype=np.uint8)
        p.add_mesh(poly, scalars="rgb", rgb=True, smooth_shading=True)
    else:
        p.add_mesh(poly, color="#d98c7a", smooth_shading=True, specular=0.2)
    p.show_grid(xtitle="x (mm)", ytitle="y (mm)", ztitle="z (mm)", font_size=8)
    if title:
        p.add_text(title, position="upper_left", font_size=10, color="black")
    lo, hi = mesh.bounds
    center = (lo + hi) / 2
    # far enough that the bounding sphere fits in pyvista's 30-degree vertical view angle
    dist = 1.15 * float(np.linalg.norm(hi - lo)) / 2 / np.tan(np.deg2rad(15.0))
    el, az = np.deg2rad(elevation_deg), np.deg2rad(azimuth_deg)
    eye = center + dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    p.camera_position = [tuple(eye), tuple(center), (0, 0, 1)]
    path = Path(path)
    p.screenshot(str(path))
    p.close()
    return path
