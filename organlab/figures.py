"""Pictures of results: an off-screen rendering of a mesh (pyvista, EGL).

pyvista is imported inside the function, so ``import organlab`` stays fast.
Off-screen rendering goes through EGL: no X server is needed.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["agreement_chart", "agreement_overlay", "mesh_snapshot"]


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


def agreement_chart(report, path):
    """Bar chart of every view's agreement with the model (``report['views'][i]['agreement']``).

    Parameters
    ----------
    report : dict
        A reconstruction report with view agreement (organlab.agreement).
    path : str or Path
        PNG to write.

    Returns
    -------
    Path
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [(Path(v["image"]).stem, v["agreement"]) for v in report["views"]]
    limit = report["agreement"]["limit"]
    vals = np.array([100 * a["disagreement"] for _, a in rows])
    fig, ax = plt.subplots(figsize=(max(6.0, 0.22 * len(rows) + 2), 3.2), layout="constrained")
    ax.bar(range(len(rows)), vals, color=["#c0392b" if not a["ok"] else "#4a7fb0" for _, a in rows])
    ax.axhline(100 * limit, color="k", ls="--", lw=1, label=f"limit {100 * limit:.2f} %")
    ax.set_xticks(range(len(rows)), [n for n, _ in rows], rotation=90, fontsize=7)
    ax.set_ylabel("silhouette unexplained (%)")
    ax.set_title(f"{report.get('session', '')}: view agreement (red: over the limit)", fontsize=10)
    ax.legend(loc="upper right", fontsize=8)
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def agreement_overlay(image, silhouette, model, path, *, title=None):
    """A view's image with its silhouette and the model's projection drawn over it.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
    silhouette : (H, W) bool
    model : (H, W) bool
        Pixels covered by the model's projection (organlab.agreement.model_mask).
    path : str or Path
        PNG to write: red = silhouette the model does not explain, blue = model
        outside the silhouette, green = both.
    title : str, optional

    Returns
    -------
    Path
    """
    from PIL import Image, ImageDraw

    img = np.asarray(image)
    rgb = np.repeat(img[..., None], 3, axis=2) if img.ndim == 2 else img[..., :3]
    out = rgb.astype(np.float32) * 0.5
    for m, colour in ((silhouette & model, (0, 200, 0)), (silhouette & ~model, (255, 0, 0)), (model & ~silhouette, (0, 80, 255))):
        out[m] = 0.4 * out[m] + 0.6 * np.array(colour, np.float32)
    pic = Image.fromarray(np.clip(out, 0, 255).astype(np.uint8))
    if title:
        ImageDraw.Draw(pic).text((6, 6), title, fill=(255, 255, 255))
    path = Path(path)
    pic.save(path)
    return path
