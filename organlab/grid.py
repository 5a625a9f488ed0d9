"""The voxel grid: origin, pitch and shape of the voxel space."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # for the annotations only (a session module is not needed to use a grid)
    from .session import Session

__all__ = ["VoxelGrid"]


@dataclass(frozen=True)
class VoxelGrid:
    """A regular grid of cubic voxels, axes x, y, z of the world frame.

    Parameters
    ----------
    origin : (3,) float64, mm, world frame
        Centre of voxel ``[0, 0, 0]``.
    voxel_size : float, mm
        Edge length of a voxel.
    shape : (3,) int
        Number of voxels along x, y, z.
    """

    origin: tuple
    voxel_size: float
    shape: tuple

    def __post_init__(self):
        origin = tuple(float(v) for v in np.asarray(self.origin, dtype=np.float64).ravel())
        shape = tuple(int(v) for v in self.shape)
        if len(origin) != 3 or len(shape) != 3:
            raise ValueError("origin and shape must have 3 elements")
        if not self.voxel_size > 0:
            raise ValueError(f"voxel_size must be > 0 mm, got {self.voxel_size}")
        if min(shape) < 1:
            raise ValueError(f"shape must be >= 1 along every axis, got {shape}")
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "voxel_size", float(self.voxel_size))

    @classmethod
    def from_roi(cls, roi_min: np.ndarray, roi_max: np.ndarray, voxel_size: float) -> VoxelGrid:
        """Grid of voxels filling the box ``[roi_min, roi_max]``.

        The first voxel's lower faces lie on ``roi_min``; the grid covers the
        roi and overshoots ``roi_max`` by less than one voxel where the roi's
        extent is not a multiple of ``voxel_size``.

        Parameters
        ----------
        roi_min, roi_max : (3,) float, mm, world frame
        voxel_size : float, mm
        """
        lo = np.asarray(roi_min, dtype=np.float64)
        hi = np.asarray(roi_max, dtype=np.float64)
        if not voxel_size > 0:
            raise ValueError(f"voxel size must be > 0 mm, got {voxel_size}")
        if np.any(hi <= lo):
            raise ValueError(f"roi min {lo.tolist()} must be < max {hi.tolist()} on every axis")
        shape = np.maximum(1, np.ceil((hi - lo) / voxel_size - 1e-9)).astype(int)
        return cls(tuple(lo + voxel_size / 2), voxel_size, tuple(shape))

    @classmethod
    def from_session(cls, session: Session, voxel_size: float = 1.0) -> VoxelGrid:
        """Grid filling the session's region of interest (``roi`` in ``session.json``).

        Parameters
        ----------
        session : organlab.session.Session
        voxel_size : float, mm
        """
        return cls.from_roi(session.roi_min, session.roi_max, voxel_size)

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.shape))

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(min, max)`` corners of the whole grid, mm, each ``(3,)``."""
        o = np.asarray(self.origin)
        lo = o - self.voxel_size / 2
        return lo, lo + np.asarray(self.shape) * self.voxel_size

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Voxel-centre coordinates along x, y and z: three 1-D arrays, mm."""
        return tuple(self.origin[i] + self.voxel_size * np.arange(self.shape[i]) for i in range(3))

    def centers(self, index: np.ndarray | None = None) -> np.ndarray:
        """World coordinates of voxel centres.

        Parameters
        ----------
        index : (N, 3) int, optional
            Voxel indices; all voxels (C order) when omitted.

        Returns
        -------
        (N, 3) float64, mm, world frame
        """
        if index is None:
            index = np.indices(self.shape).reshape(3, -1).T
        return np.asarray(self.origin) + np.asarray(index, dtype=np.float64) * self.voxel_size

    def volume_of(self, occupancy: np.ndarray) -> float:
        """Volume of the occupied voxels, mm^3."""
        return float(np.count_nonzero(occupancy)) * self.voxel_size**3
