"""Constants, the result type and input validation of :mod:`organlab.coloring`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..errors import OrganlabError
from ..grid import VoxelGrid
from ..nbcam import pack_cameras

#: Default photo-consistency threshold, grey levels (standard deviation).
DEFAULT_THRESHOLD = 18.0

#: Default spatial support of a carve (inconsistent voxels in a 3 x 3 neighbourhood).
DEFAULT_SUPPORT = 3

_AXES = "xyz"


class VisibilityConstraintError(OrganlabError, ValueError):
    """The cameras do not allow a layered (single sweep) voxel colouring."""


@dataclass(frozen=True)
class ColoringResult:
    """What :func:`color_voxels` returns.

    Attributes
    ----------
    occupancy : (nx, ny, nz) bool
        The solid after colouring: candidates minus carved voxels.
    colors : (nx, ny, nz, 3) uint8
        RGB colour of every coloured voxel (mean of its visible pixels);
        zeros elsewhere.
    colored : (nx, ny, nz) bool
        The voxels that were seen and kept, i.e. those with a colour.
    n_candidates : int
        Voxels tested (hull or whole grid).
    n_carved : int
        Voxels removed.
    n_carved_background : int
        Of those, voxels carved because a view saw mostly background through them.
    n_visible : int
        Kept voxels that some view sees (== ``colored.sum()``).
    n_hidden : int
        Kept voxels that no view sees (interior).
    n_untested : int
        Kept voxels seen by fewer pixels than ``completeness`` asks.
    seconds : float
        Wall time.
    method : str
    sweep : str or None
        Layered sweep direction, e.g. ``"-z"`` (planes from the top down);
        None for space carving.
    iterations : int
        Passes (1 for voxel colouring).
    threshold : float
        The threshold used (the automatic one when ``automatic``).
    automatic : bool
        The threshold was measured (``threshold="auto"``).
    n_restored : int
        Carved voxels the silhouette guard put back.
    noise : float or None
        Measured pixel noise, grey levels (automatic threshold only).
    gains : tuple of float or None
        Per-view exposure gains divided out (``exposure=True``).
    support : int
        The spatial support used (resolved from ``support='auto'``).
    """

    occupancy: np.ndarray
    colors: np.ndarray
    colored: np.ndarray
    n_candidates: int
    n_carved: int
    n_carved_background: int
    n_visible: int
    n_hidden: int
    n_untested: int
    seconds: float
    method: str
    sweep: str | None
    iterations: int
    threshold: float
    automatic: bool = False
    n_restored: int = 0
    noise: float | None = None
    gains: tuple | None = None
    support: int = DEFAULT_SUPPORT

    def stats(self) -> dict:
        """The scalar fields as a JSON-ready dict."""
        return {
            "method": self.method,
            "threshold": self.threshold,
            "sweep": self.sweep,
            "iterations": self.iterations,
            "n_candidates": self.n_candidates,
            "n_carved": self.n_carved,
            "n_carved_background": self.n_carved_background,
            "n_visible": self.n_visible,
            "n_hidden": self.n_hidden,
            "n_untested": self.n_untested,
            "seconds": self.seconds,
            "automatic": self.automatic,
            "n_restored": self.n_restored,
            "noise": self.noise,
            "exposure_gains": None if self.gains is None else list(self.gains),
            "support": self.support,
        }


# =====================================================================

# =====================================================================
# validation and packing
# =====================================================================
def _check_inputs(images, cameras, grid, masks):
    if not isinstance(grid, VoxelGrid):
        raise TypeError(f"grid must be an organlab.grid.VoxelGrid, got {type(grid).__name__}")
    cameras = [cameras] if isinstance(cameras, Camera) else list(cameras)
    if isinstance(images, np.ndarray) and images.ndim in (2, 3) and images.dtype == np.uint8 and len(cameras) == 1:
        if images.ndim == 2 or images.shape[-1] == 3:
            images = [images]
    images = list(images)
    if len(images) != len(cameras):
        raise ValueError(f"got {len(images)} images but {len(cameras)} cameras: give one camera per image")
    if not images:
        raise ValueError("no views: give at least one image and its camera")
    for i, c in enumerate(cameras):
        if not isinstance(c, Camera):
            raise TypeError(f"camera {i} must be an organlab.camera.Camera, got {type(c).__name__}")
    shapes = set()
    for i, (im, cam) in enumerate(zip(images, cameras)):
        a = np.asarray(im)
        if a.dtype != np.uint8 or not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
            raise ValueError(f"image {i} must be an (H, W) or (H, W, 3) uint8 array, got {a.dtype} {a.shape}")
        if (a.shape[1], a.shape[0]) != tuple(cam.image_size):
            raise ValueError(
                f"image {i} is {a.shape[1]}x{a.shape[0]} px but its camera's image_size is "
                f"{cam.image_size[0]}x{cam.image_size[1]}"
            )
        shapes.add(a.shape)
    if len(shapes) != 1:
        raise ValueError(f"all images must have the same shape, got {sorted(shapes)}")
    shape = shapes.pop()
    stack = np.empty((len(images),) + shape[:2] + (shape[2] if len(shape) == 3 else 1,), np.uint8)
    for i, im in enumerate(images):
        stack[i] = np.asarray(im).reshape(stack.shape[1:])
    bg = None
    if masks is not None:
        masks = list(masks)
        if len(masks) != len(images):
            raise ValueError(f"got {len(masks)} masks but {len(images)} images: give one mask per image")
        bg = np.empty(stack.shape[:3], np.uint8)
        for i, m in enumerate(masks):
            m = np.asarray(m)
            if m.shape != shape[:2]:
                raise ValueError(f"mask {i} has shape {m.shape} but image {i} has (H, W) = {shape[:2]}")
            bg[i] = m == 0
    return stack, cameras, pack_cameras(cameras), bg


def _check_occupancy(occupancy, grid):
    occ = np.asarray(occupancy)
    if occ.shape != grid.shape:
        raise ValueError(f"occupancy has shape {occ.shape} but the grid's shape is {grid.shape}")
    if occ.dtype != bool:
        raise ValueError(f"occupancy must be a bool array, got {occ.dtype}")
    return occ



def _completeness_rule(completeness):
    if completeness is None:
        return 1, 0.0
    if isinstance(completeness, bool):
        raise ValueError(f"completeness must be None, an integer >= 1 or a fraction in (0, 1), got {completeness!r}")
    if isinstance(completeness, (int, np.integer)):
        if completeness < 1:
            raise ValueError(f"completeness must be an integer >= 1 (visible pixels), got {completeness}")
        return int(completeness), 0.0
    c = float(completeness)
    if not 0.0 < c < 1.0:
        raise ValueError(f"completeness as a fraction must lie in (0, 1), got {completeness!r}")
    return 1, c

