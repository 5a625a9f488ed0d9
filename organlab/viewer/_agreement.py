"""Per-view agreement of a hull with the silhouettes (the viewer's read-out).

This only *calls* stage functions: :meth:`organlab.camera.Camera.project` to
project the mesh and the package's triangle rasteriser to fill it.  (A public
agreement function for the pipeline is the subject of issue 15; once it lands
the viewer should call it instead.)
"""

from __future__ import annotations

import numpy as np


def hull_mask(mesh, camera):
    """Pixels covered by a closed mesh seen by a camera, (H, W) bool."""
    from .._raster import fill_triangles

    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        uv = camera.project(mesh.vertices)
    return fill_triangles(uv, mesh.faces, (camera.height, camera.width))


def iou(a, b):
    """Intersection over union of two bool masks (1.0 when both are empty)."""
    a = np.asarray(a, bool)
    b = np.asarray(b, bool)
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else np.count_nonzero(a & b) / union


def view_agreement(mesh, cameras, masks):
    """IoU of the mesh's projection with each view's silhouette.

    Parameters
    ----------
    mesh : organlab.surface.Mesh
        mm, world frame.
    cameras : sequence of Camera
    masks : sequence of (H, W) bool

    Returns
    -------
    agreement : (n_views,) float64 in [0, 1]
    """
    return np.array([iou(hull_mask(mesh, c), m) for c, m in zip(cameras, masks)], dtype=np.float64)
