"""Pure helpers of the viewer: poses, thumbnails, overlays, surface voxels.

Nothing here talks to a browser; :mod:`._live` turns these arrays into viser
scene nodes.  Conventions: world frame = turntable frame, mm; cameras are
:class:`organlab.camera.Camera` (world to camera, OpenCV axes), which is also
the convention of viser's frustums and client cameras.
"""

from __future__ import annotations

import numpy as np

# colours (RGB uint8)
SILHOUETTE_RGB = (40, 200, 80)
HULL_RGB = (230, 40, 40)
VOXEL_RGB = (90, 170, 240)
THUMB_WIDTH = 192


def quat_wxyz(R):
    """Unit quaternion ``(w, x, y, z)`` of a 3x3 rotation matrix, float64 (4,)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = np.zeros(4)
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.asarray(q, dtype=np.float64)
    return q / np.linalg.norm(q)


def camera_pose(camera):
    """Pose of a camera in the world, as viser wants it.

    Returns
    -------
    wxyz : (4,) float64
        Rotation camera to world (``R_world_cam = R.T``).
    position : (3,) float64, mm, world frame
        The camera centre.
    fov : float, rad
        Vertical field of view.
    aspect : float
        Width over height.
    """
    w, h = camera.image_size
    fov = 2.0 * np.arctan2(h / 2.0, camera.K[1, 1])
    return quat_wxyz(camera.R.T), np.asarray(camera.center, np.float64), float(fov), w / h


def frustum_scale(fov, aspect, depth):
    """viser's frustum ``scale`` that puts the image plane at ``depth`` (scene units).

    viser normalises a frustum to unit volume-ish size: its depth is
    ``scale / cbrt(tan(fov/2)^2 * aspect / 3)``.
    """
    y = np.tan(fov / 2.0)
    return float(depth * np.cbrt(y * y * aspect / 3.0))


def thumbnail(image, width=THUMB_WIDTH):
    """An image shrunk to ``width`` px (area averaging), RGB uint8 (h, width, 3)."""
    import cv2

    img = np.asarray(image)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = np.ascontiguousarray(img[..., :3], dtype=np.uint8)
    h, w = img.shape[:2]
    if w <= width:
        return img
    return cv2.resize(img, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)


def overlay(image, silhouette=None, hull=None):
    """The photo with its silhouette tinted and the hull's outline drawn.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
    silhouette : (H, W) bool, optional
        Tinted green.
    hull : (H, W) bool, optional
        Projected hull; its outline is drawn red, 2 px.

    Returns
    -------
    (H, W, 3) uint8, a new array
    """
    import cv2

    img = np.asarray(image)
    out = np.repeat(img[..., None], 3, axis=2) if img.ndim == 2 else img[..., :3]
    out = np.array(out, dtype=np.uint8)
    if silhouette is not None:
        m = np.asarray(silhouette, bool)
        tint = np.asarray(SILHOUETTE_RGB, np.float32)
        out[m] = (0.55 * out[m] + 0.45 * tint).astype(np.uint8)
    if hull is not None:
        contours, _ = cv2.findContours(np.asarray(hull, np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, contours, -1, HULL_RGB, 2)
    return out


def surface_voxels(occupancy):
    """Occupied voxels with at least one empty 6-neighbour (or on the grid's border).

    Parameters
    ----------
    occupancy : (nx, ny, nz) bool

    Returns
    -------
    (nx, ny, nz) bool, a new array
    """
    occ = np.asarray(occupancy, bool)
    p = np.pad(occ, 1)
    inner = (
        p[:-2, 1:-1, 1:-1] & p[2:, 1:-1, 1:-1] & p[1:-1, :-2, 1:-1]
        & p[1:-1, 2:, 1:-1] & p[1:-1, 1:-1, :-2] & p[1:-1, 1:-1, 2:]
    )
    return occ & ~inner


def height_colors(points, lo, hi, base=VOXEL_RGB):
    """A colour per point, darker low and lighter high (depth cue for unlit points).

    Returns
    -------
    (N, 3) uint8
    """
    z = np.asarray(points)[:, 2]
    s = np.clip((z - lo) / max(hi - lo, 1e-9), 0.0, 1.0)[:, None]
    return (np.asarray(base, np.float32) * (0.55 + 0.45 * s)).clip(0, 255).astype(np.uint8)


def view_palette(n):
    """``n`` distinct colours (a hue wheel), (n, 3) uint8: the colour of each view."""
    import colorsys

    return np.array(
        [[round(255 * c) for c in colorsys.hsv_to_rgb(i / max(n, 1), 0.85, 0.95)] for i in range(n)], np.uint8
    ).reshape(-1, 3)


def near_hull(views, occupancy, shell):
    """Carved voxels within ``shell`` voxels (chessboard distance) of the hull.

    Parameters
    ----------
    views : (nx, ny, nz) int16
        From :func:`organlab.carving.carving_views`.
    occupancy : (nx, ny, nz) bool
    shell : int

    Returns
    -------
    (nx, ny, nz) bool
    """
    from scipy import ndimage

    grown = ndimage.binary_dilation(occupancy, structure=np.ones((3, 3, 3), bool), iterations=int(shell))
    return grown & (views >= 0)


def roi_stats(lo, hi, voxel_size, tolerance=0):
    """Voxel count and working memory of a region of interest.

    Memory is that of :func:`organlab.carving.hull_field` (``(tolerance + 1)
    * 4 + 2`` bytes per voxel) plus the field and occupancy kept (5 bytes).

    Returns
    -------
    n_voxels : int
    bytes : int
    """
    ext = np.asarray(hi, float) - np.asarray(lo, float)
    shape = np.maximum(1, np.ceil(ext / voxel_size - 1e-9)).astype(np.int64)
    n = int(np.prod(shape))
    return n, n * ((int(tolerance) + 1) * 4 + 2 + 5)


def human_bytes(n):
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000.0
    return f"{n:.1f} GB"


def aaa_geometry(measures):
    """What the scene draws of AAA measures (:class:`organlab.surface.AAAMeasures`), mm, world frame.

    Returns
    -------
    dict
        ``centreline`` (K-1, 2, 3) float32: consecutive centreline points as segments;
        ``ring`` (M, 2, 3) float32: the closed contour of the maximum-diameter section;
        ``disc_vertices`` (M + 1, 3) float32 and ``disc_faces`` (M, 3) uint32: that section
        as a fan about the contour's centroid; ``diameter`` (1, 2, 3) float32: the two
        contour points farthest apart (the maximum Feret diameter); ``label_at`` (3,) float64.
    """
    from scipy.spatial import ConvexHull
    from scipy.spatial.distance import pdist, squareform

    c = np.asarray(measures.centreline, np.float64)
    sec = np.asarray(measures.max_section, np.float64)
    if np.allclose(sec[0], sec[-1]):
        sec = sec[:-1]  # find_contours closes the contour by repeating its first point
    ring = np.stack([sec, np.roll(sec, -1, axis=0)], axis=1)
    m = len(sec)
    centre = sec.mean(axis=0)
    faces = np.stack([np.zeros(m, np.int64), 1 + np.arange(m), 1 + (np.arange(m) + 1) % m], axis=1)
    # the Feret diameter lies between two convex-hull vertices of the (planar) section
    u, s, vt = np.linalg.svd(sec - centre, full_matrices=False)
    hull = sec[ConvexHull((sec - centre) @ vt[:2].T).vertices]
    i, j = np.unravel_index(np.argmax(squareform(pdist(hull))), (len(hull), len(hull)))
    return {
        "centreline": np.stack([c[:-1], c[1:]], axis=1).astype(np.float32),
        "ring": ring.astype(np.float32),
        "disc_vertices": np.vstack([centre, sec]).astype(np.float32),
        "disc_faces": faces.astype(np.uint32),
        "diameter": np.array([[hull[i], hull[j]]], np.float32),
        "label_at": hull[i] + 0.1 * (hull[i] - centre),
    }
