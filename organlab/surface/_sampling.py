"""Trilinear samples of a hull field, dense or stored in its narrow band.

:func:`organlab.surface.measure_aaa` cuts the lumen by planes and needs the
field at arbitrary points; on a ``BandField`` (``hull_field(...,
sparse=True)``) it samples the band directly instead of densifying it (at
0.25 mm the dense field alone is 1 GB).  Samples follow
``scipy.ndimage.map_coordinates(order=1, mode='constant')``: a point outside
``[0, n - 1]`` on any axis gets ``cval``, the others interpolate the 8
surrounding voxels.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def _band_value(states, index, values, B, i, j, k):
    bx, by, bz = i // B, j // B, k // B
    s = states[bx, by, bz]
    if s == 2:
        return values[index[bx, by, bz], i - bx * B, j - by * B, k - bz * B]
    return np.float32(1.5) if s == 1 else np.float32(-0.5)


@njit(cache=True, inline="always")
def _trilinear(states, index, values, B, nx, ny, nz, x, y, z, cval):
    if not (0.0 <= x <= nx - 1 and 0.0 <= y <= ny - 1 and 0.0 <= z <= nz - 1):
        return cval
    i0 = min(int(x), nx - 2) if nx > 1 else 0
    j0 = min(int(y), ny - 2) if ny > 1 else 0
    k0 = min(int(z), nz - 2) if nz > 1 else 0
    fx, fy, fz = x - i0, y - j0, z - k0
    acc = 0.0
    for di in range(2):
        wx = fx if di else 1.0 - fx
        if wx == 0.0:
            continue
        for dj in range(2):
            wy = fy if dj else 1.0 - fy
            if wy == 0.0:
                continue
            for dk in range(2):
                wz = fz if dk else 1.0 - fz
                if wz == 0.0:
                    continue
                acc += wx * wy * wz * _band_value(states, index, values, B, i0 + di, j0 + dj, k0 + dk)
    return acc


# threads pay from about 10^5 points: a section's 10^3-10^4 took 35 ms on two threads of a busy
# machine against 0.06 ms on one (1 mm sample)
@njit(cache=True, parallel=True, nogil=True)
def _sample_band(states, index, values, B, nx, ny, nz, ijk, cval, out):
    for p in prange(ijk.shape[0]):
        out[p] = _trilinear(states, index, values, B, nx, ny, nz, ijk[p, 0], ijk[p, 1], ijk[p, 2], cval)


@njit(cache=True, nogil=True)
def _sample_band_serial(states, index, values, B, nx, ny, nz, ijk, cval, out):
    for p in range(ijk.shape[0]):
        out[p] = _trilinear(states, index, values, B, nx, ny, nz, ijk[p, 0], ijk[p, 1], ijk[p, 2], cval)


_PARALLEL_FROM = 100_000


@njit(cache=True, parallel=True, nogil=True)
def _above_band(states, index, values, B, nx, ny, nz, base, step, level, cval, out):
    """``out[a, b, c] = trilinear(base + step * (a, b, c)) > level`` (as :func:`_sample_band`), a point
    whose 8 neighbours lie in one inside or outside block taken at that block's value: its samples are
    a weighted mean of equal values (1.5 or -0.5), whose rounding cannot cross a level more than 1e-6 away."""
    for a in prange(out.shape[0]):
        x = base[0] + a * step
        for b in range(out.shape[1]):
            y = base[1] + b * step
            for c in range(out.shape[2]):
                z = base[2] + c * step
                if 0.0 <= x <= nx - 1 and 0.0 <= y <= ny - 1 and 0.0 <= z <= nz - 1:
                    i0 = min(int(x), nx - 2) if nx > 1 else 0
                    j0 = min(int(y), ny - 2) if ny > 1 else 0
                    k0 = min(int(z), nz - 2) if nz > 1 else 0
                    bx, by, bz = i0 // B, j0 // B, k0 // B
                    if (bx == (i0 + 1) // B and by == (j0 + 1) // B and bz == (k0 + 1) // B
                            and states[bx, by, bz] != 2):
                        v = 1.5 if states[bx, by, bz] == 1 else -0.5
                        if abs(v - level) > 1e-6:
                            out[a, b, c] = v > level
                            continue
                out[a, b, c] = _trilinear(states, index, values, B, nx, ny, nz, x, y, z, cval) > level


class FieldSampler:
    """Trilinear samples of a field on a voxel grid.

    Parameters
    ----------
    volume : (nx, ny, nz) array or BandField
        Values at the voxel centres (a ``BandField`` is read in its band).
    origin : (3,) float64, mm, world frame
        Centre of voxel ``(0, 0, 0)`` of ``volume``.
    voxel_size : float, mm
    cval : float
        Value outside the volume.
    """

    def __init__(self, volume, origin, voxel_size, cval):
        self.volume = volume
        self.origin = np.asarray(origin, dtype=np.float64)
        self.voxel_size = float(voxel_size)
        self.cval = float(cval)
        self.band = not isinstance(volume, np.ndarray)

    def __call__(self, points):
        """Field at ``points`` (..., 3) float64, mm, world frame; returns (...) float64."""
        pts = np.asarray(points, dtype=np.float64)
        return self.at_indices((pts - self.origin) / self.voxel_size)

    def at_indices(self, ijk):
        """Field at fractional voxel indices ``ijk`` (..., 3) float64; returns (...) float64."""
        shape = ijk.shape[:-1]
        ijk = np.ascontiguousarray(ijk, dtype=np.float64).reshape(-1, 3)
        if not self.band:
            from scipy import ndimage

            out = ndimage.map_coordinates(self.volume, ijk.T, order=1, mode="constant", cval=self.cval)
            return out.reshape(shape)
        f = self.volume
        nx, ny, nz = f.shape
        out = np.empty(len(ijk), dtype=np.float64)
        kernel = _sample_band if len(ijk) >= _PARALLEL_FROM else _sample_band_serial
        kernel(f.states, f.index, f.values, f.block, nx, ny, nz, ijk, self.cval, out)
        return out.reshape(shape)

    def above(self, lo, shape, step, level):
        """``field > level`` at the centres of a grid ``step`` voxels apart from voxel ``lo`` + (step - 1) / 2.

        Parameters
        ----------
        lo : (3,) int
            First voxel (indices into ``volume``) of the sampled box.
        shape : (3,) int
            Samples per axis.
        step : int
            Voxels between samples (1: the voxel centres themselves).
        level : float

        Returns
        -------
        (shape) bool
        """
        shape = tuple(int(s) for s in shape)
        out = np.empty(shape, dtype=bool)
        base = np.asarray(lo, dtype=np.float64) + 0.5 * (step - 1)
        if self.band:  # one pass, inside and outside blocks read once (the sample, 0.25 mm: 0.56 -> 0.17 s CPU)
            f = self.volume
            _above_band(f.states, f.index, f.values, f.block, *f.shape, base, float(step), float(level),
                        self.cval, out)
            return out
        j, k = np.meshgrid(np.arange(shape[1]), np.arange(shape[2]), indexing="ij")
        plane = np.stack([np.zeros_like(j), j, k], axis=-1).astype(np.float64) * step + base
        for i in range(shape[0]):  # a plane at a time: no (N, 3) coordinates of the whole box
            plane[..., 0] = base[0] + i * step
            out[i] = self.at_indices(plane) > level
        return out
