"""Where colouring carved: regions, depths below the hull, an unwrapped depth map and its picture."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage

from ..grid import VoxelGrid

_PHI_STEP_DEG = 5.0
_Z_STEP_MM = 2.0
_MIN_REGION_MM3 = 20.0
_MAX_REGIONS = 12


def carved_where(hull: np.ndarray, occupancy: np.ndarray, grid: VoxelGrid) -> dict:
    """Regions carved from the hull and the carved depth unwrapped about the table axis.

    Parameters
    ----------
    hull, occupancy : (nx, ny, nz) bool
        Before and after colouring, on ``grid``.
    grid : VoxelGrid

    Returns
    -------
    dict
        ``regions``: up to 12 connected carved regions of at least 20 mm^3,
        largest first, each ``{"centre_mm", "volume_mm3", "max_depth_mm"}``
        (world frame; depth = distance below the hull's surface);
        ``depth_map``: ``{"phi_step_deg", "z0_mm", "z_step_mm", "mm"}`` the
        largest carved depth per bin of table angle (rows) and height
        (columns), mm, rounded to 0.1 mm.

    Examples
    --------
    >>> g = VoxelGrid.from_roi(np.zeros(3), np.full(3, 20.0), 1.0)
    >>> hull = np.ones(g.shape, bool); occ = hull.copy(); occ[8:13, 0:4, 8:13] = False
    >>> w = carved_where(hull, occ, g)
    >>> w["regions"][0]["volume_mm3"], w["regions"][0]["max_depth_mm"]
    (100.0, 4.0)
    """
    carved = hull & ~occupancy
    h = float(grid.voxel_size)
    origin = np.asarray(grid.origin, np.float64)
    out = {"regions": [], "depth_map": None}
    if not carved.any():
        return out
    depth = ndimage.distance_transform_edt(np.pad(hull, 1)) [1:-1, 1:-1, 1:-1] * h  # centre to the hull's outside
    depth = np.maximum(depth - 0.5 * h, 0.0) + 0.5 * h  # a carved surface voxel: half a voxel deep
    lab, n = ndimage.label(carved, structure=np.ones((3, 3, 3)))
    vols = ndimage.sum(carved, lab, np.arange(1, n + 1)) * h**3
    order = np.argsort(-vols)
    for r in order[:_MAX_REGIONS]:
        if vols[r] < _MIN_REGION_MM3:
            break
        idx = np.argwhere(lab == r + 1)
        out["regions"].append({
            "centre_mm": [round(float(v), 1) for v in origin + idx.mean(0) * h],
            "volume_mm3": round(float(vols[r]), 1),
            "max_depth_mm": round(float(depth[tuple(idx.T)].max()), 1),
        })
    idx = np.argwhere(carved)
    p = origin + idx * h
    cx, cy = origin[:2] + 0.5 * (np.array(hull.shape[:2]) - 1) * h
    phi = np.degrees(np.arctan2(p[:, 1] - cy, p[:, 0] - cx)) % 360.0
    hz = np.argwhere(hull)[:, 2]
    z0 = origin[2] + hz.min() * h
    nz = int(np.ceil(((hz.max() - hz.min()) * h + h) / _Z_STEP_MM))
    m = np.zeros((int(360 / _PHI_STEP_DEG), max(nz, 1)))
    ip = np.minimum((phi / _PHI_STEP_DEG).astype(int), m.shape[0] - 1)
    iz = np.clip(((p[:, 2] - z0) / _Z_STEP_MM).astype(int), 0, m.shape[1] - 1)
    np.maximum.at(m, (ip, iz), depth[tuple(idx.T)])
    out["depth_map"] = {"phi_step_deg": _PHI_STEP_DEG, "z0_mm": round(float(z0), 2), "z_step_mm": _Z_STEP_MM,
                        "mm": np.round(m, 1).tolist()}
    return out


def carved_depth_picture(coloring: dict, path: str | Path, *, title: str = "") -> Path:
    """Draw a report's ``coloring.depth_map`` (carved depth over the hull, unwrapped) to a PNG.

    Parameters
    ----------
    coloring : dict
        The report's ``coloring`` entry (with ``depth_map``, from :func:`carved_where`).
    path : str or Path
    title : str

    Returns
    -------
    Path
        ``path``: table angle across (0-360 degrees), height up, colour =
        depth carved below the hull (mm, scale bar at the right); grey
        where nothing was carved.
    """
    import cv2

    path = Path(path)
    dm = (coloring or {}).get("depth_map")
    m = np.zeros((72, 40)) if dm is None else np.asarray(dm["mm"], np.float64)
    top = max(float(m.max()), 1.0)
    img = cv2.applyColorMap(np.clip(255 * m / top, 0, 255).astype(np.uint8).T[::-1], cv2.COLORMAP_INFERNO)
    img[(m.T[::-1] <= 0)] = (90, 90, 90)
    sc = 8
    img = cv2.resize(img, (img.shape[1] * sc, img.shape[0] * sc), interpolation=cv2.INTER_NEAREST)
    bar = cv2.applyColorMap(np.linspace(255, 0, img.shape[0]).astype(np.uint8)[:, None].repeat(20, 1), cv2.COLORMAP_INFERNO)
    canvas = np.full((img.shape[0] + 60, img.shape[1] + 110, 3), 255, np.uint8)
    canvas[40:40 + img.shape[0], 10:10 + img.shape[1]] = img
    canvas[40:40 + img.shape[0], img.shape[1] + 20:img.shape[1] + 40] = bar
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(canvas, title or "carved depth below the hull", (10, 25), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(canvas, f"{top:.1f} mm", (img.shape[1] + 44, 52), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(canvas, "0", (img.shape[1] + 44, 40 + img.shape[0]), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(canvas, "table angle 0-360 deg ->, height up", (10, img.shape[0] + 55), font, 0.45, (0, 0, 0), 1,
                cv2.LINE_AA)
    cv2.imwrite(str(path), canvas)
    return path
