"""The hull field stored in a narrow band: plain data on the ground floor.

:func:`organlab.carving.hull_field` (``sparse=True``) makes it;
:func:`organlab.surface.mesh_from_field` meshes it (on the band only);
``voxels.npz`` stores it (:meth:`BandField.to_arrays`,
:meth:`BandField.from_arrays`).  The type and its dense views live here,
below the stages, so that carving (which writes it) and surface (which reads
it) need not import each other.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from numba import njit, prange

from .errors import OrganlabError
from .grid import VoxelGrid

__all__ = ["BandField", "OUTSIDE", "INSIDE", "BAND"]

#: Block states: every voxel -0.5, every voxel 1.5, values stored.
OUTSIDE, INSIDE, BAND = 0, 1, 2


class BandField:
    """The hull field, stored in a narrow band around the surface.

    Voxels are grouped in cubic blocks of ``block`` voxels a side.  A block is
    ``OUTSIDE`` (every voxel -0.5), ``INSIDE`` (every voxel 1.5) or ``BAND``
    (values stored).  Made by ``hull_field(..., sparse=True)``.

    Attributes
    ----------
    grid : VoxelGrid
    block : int
        Block edge, voxels.
    states : (bx, by, bz) int8
        Per block: 0 outside, 1 inside, 2 band; ``bx = ceil(nx / block)``...
    index : (bx, by, bz) int32
        Row of each band block in ``values``, -1 for the others.
    values : (n_band, block, block, block) float32
        The field in the band blocks (axes x, y, z; voxels beyond the grid
        hold -0.5).
    """

    def __init__(self, grid: VoxelGrid, block: int, states: np.ndarray, index: np.ndarray, values: np.ndarray) -> None:
        self.grid = grid
        self.block = int(block)
        self.states = states
        self.index = index
        self.values = values

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.grid.shape)

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.float32)

    @property
    def n_band_voxels(self) -> int:
        """Voxels whose value is stored (band blocks times block volume)."""
        return int(self.values.shape[0]) * self.block**3

    @property
    def nbytes(self) -> int:
        return int(self.states.nbytes + self.index.nbytes + self.values.nbytes)

    def min(self) -> float:
        """Smallest value of the field."""
        lo = [float(self.values.min())] if len(self.values) else []
        if (self.states == OUTSIDE).any():
            lo.append(-0.5)
        if (self.states == INSIDE).any():
            lo.append(1.5)
        return min(lo)

    def dense(self) -> np.ndarray:
        """The dense field, ``grid.shape`` float32 (as ``hull_field`` returns)."""
        out = np.empty(self.grid.shape, dtype=np.float32)
        _fill_dense(out, self.states, self.index, self.values, self.block)
        return out

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        a = self.dense()
        return a if dtype is None else a.astype(dtype)

    def occupancy(self) -> np.ndarray:
        """Voxel centres inside the hull (field >= 0.5), ``grid.shape`` bool."""
        # zeros (fresh pages from the system, mapped when first written) and only the inside and band blocks
        # written: at 0.25 mm the sample's 250 MB occupancy is mostly outside blocks
        out = np.zeros(self.grid.shape, dtype=np.bool_)
        _fill_occupancy(out, self.states, self.index, self.values, self.block)
        return out

    def n_inside(self) -> int:
        """Number of voxel centres inside the hull (field >= 0.5)."""
        return int(_count_inside(self.states, self.index, self.values, self.block, np.asarray(self.grid.shape)))

    # ----------------------------------------------------------- storage
    def to_arrays(self, *, prefix: str = "field_") -> dict[str, np.ndarray]:
        """The field as plain arrays, for ``np.savez_compressed`` (``voxels.npz``).

        Only the band blocks' values are stored, so the size grows with the
        surface, not the volume.  The band blocks' rows are put in C order of
        their block (the order of ``states == 2``), so the index is implied.

        Parameters
        ----------
        prefix : str
            Prepended to the array names.

        Returns
        -------
        dict of str -> ndarray
            ``{prefix}block`` : () int64, block edge, voxels;
            ``{prefix}states`` : (bx, by, bz) int8, 0 outside (every voxel
            -0.5), 1 inside (every voxel 1.5), 2 band, with
            ``bx = ceil(nx / block)``...;
            ``{prefix}values`` : (n_band, block, block, block) float32, the
            band blocks' values in C order of their block (axes x, y, z;
            voxels beyond the grid hold -0.5).
        """
        band = self.states == BAND
        rows = self.index[band]
        values = self.values
        if not np.array_equal(rows, np.arange(len(rows))):
            values = values[rows]
        return {
            f"{prefix}block": np.int64(self.block),
            f"{prefix}states": np.ascontiguousarray(self.states, dtype=np.int8),
            f"{prefix}values": np.ascontiguousarray(values, dtype=np.float32),
        }

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray], grid: VoxelGrid, *, prefix: str = "field_",
                    source: str | Path = "voxels.npz") -> BandField:
        """The field back from :meth:`to_arrays`' arrays, checked.

        Parameters
        ----------
        arrays : mapping of str -> ndarray
            Holds ``{prefix}block``, ``{prefix}states``, ``{prefix}values``
            (an ``np.load`` result works).
        grid : VoxelGrid
            The grid the field samples (its shape fixes the states' shape).
        prefix : str
        source : str or Path
            Named in the errors (the file read).

        Returns
        -------
        BandField

        Raises
        ------
        OrganlabError
            One line naming ``source`` and the array, when an array is
            missing, or its shape, dtype or content does not fit the others.
        """
        def bad(name, why):
            return OrganlabError(f"{source}: {prefix}{name}: {why}; rewrite it with 'organlab reconstruct'")

        got = {}
        for name in ("block", "states", "values"):
            try:
                got[name] = np.asarray(arrays[prefix + name])
            except KeyError:
                raise bad(name, "missing") from None
        block, states, values = got["block"], got["states"], got["values"]
        if block.shape != () or block.dtype.kind not in "iu" or not 1 <= int(block) <= 1024:
            raise bad("block", f"{block.dtype} {block.shape}, expected one integer from 1 to 1024")
        B = int(block)
        nb = tuple(-(-int(n) // B) for n in grid.shape)
        if states.dtype != np.int8 or states.shape != nb:
            raise bad("states", f"{states.dtype} {states.shape}, expected int8 {nb} (grid {tuple(grid.shape)} "
                                f"in blocks of {B})")
        if states.size and (states.min() < OUTSIDE or states.max() > BAND):
            raise bad("states", "values other than 0 (outside), 1 (inside), 2 (band)")
        band = states == BAND
        n = int(band.sum())
        if values.dtype != np.float32 or values.shape != (n, B, B, B):
            raise bad("values", f"{values.dtype} {values.shape}, expected float32 {(n, B, B, B)} "
                                f"(one block per band block of {prefix}states)")
        if n and not (values.min() >= -0.5 and values.max() <= 1.5):  # NaN fails too
            raise bad("values", "outside the field's range [-0.5, 1.5]")
        index = np.full(nb, -1, dtype=np.int32)
        index[band] = np.arange(n, dtype=np.int32)
        return cls(grid, B, np.ascontiguousarray(states), index, np.ascontiguousarray(values))

    def __repr__(self) -> str:
        return (
            f"BandField(shape={self.shape}, block={self.block}, band_blocks={len(self.values)}, "
            f"{self.nbytes / 1e6:.1f} MB)"
        )


# --------------------------------------------------------- dense views
@njit(cache=True, parallel=True)
def _fill_dense(out, states, index, values, B):
    nx, ny, nz = out.shape
    for bx in prange(states.shape[0]):
        for by in range(states.shape[1]):
            for bz in range(states.shape[2]):
                s = states[bx, by, bz]
                q = index[bx, by, bz]
                for i in range(bx * B, min(bx * B + B, nx)):
                    for j in range(by * B, min(by * B + B, ny)):
                        for k in range(bz * B, min(bz * B + B, nz)):
                            if s == 2:
                                out[i, j, k] = values[q, i - bx * B, j - by * B, k - bz * B]
                            elif s == 1:
                                out[i, j, k] = 1.5
                            else:
                                out[i, j, k] = -0.5


@njit(cache=True, parallel=True)
def _fill_occupancy(out, states, index, values, B):
    """The inside and band blocks of ``out`` (zeros: the outside blocks are left as they are)."""
    nx, ny, nz = out.shape
    for bx in prange(states.shape[0]):
        for by in range(states.shape[1]):
            for bz in range(states.shape[2]):
                s = states[bx, by, bz]
                if s == 0:
                    continue
                q = index[bx, by, bz]
                for i in range(bx * B, min(bx * B + B, nx)):
                    for j in range(by * B, min(by * B + B, ny)):
                        for k in range(bz * B, min(bz * B + B, nz)):
                            if s == 2:
                                out[i, j, k] = values[q, i - bx * B, j - by * B, k - bz * B] >= 0.5
                            else:
                                out[i, j, k] = True


@njit(cache=True)
def _count_inside(states, index, values, B, shape):
    nx, ny, nz = shape[0], shape[1], shape[2]
    n = 0
    for bx in range(states.shape[0]):
        for by in range(states.shape[1]):
            for bz in range(states.shape[2]):
                s = states[bx, by, bz]
                if s == 0:
                    continue
                q = index[bx, by, bz]
                for i in range(bx * B, min(bx * B + B, nx)):
                    for j in range(by * B, min(by * B + B, ny)):
                        for k in range(bz * B, min(bz * B + B, nz)):
                            if s == 1 or values[q, i - bx * B, j - by * B, k - bz * B] >= 0.5:
                                n += 1
    return n
