"""Numba kernels of the camera model (ground floor): :meth:`organlab.camera.Camera.project` for one point,
:func:`organlab.camera.undistort` for many.

The voxel kernels (:mod:`organlab.carving`, :mod:`organlab.coloring`) project
millions of points one at a time inside numba loops; they share the camera
packing and the projection written here, term for term as in
:mod:`organlab.camera` (same floating-point operations, same order), so that
they agree with :meth:`Camera.project` to rounding.

Packed camera, ``(N_CP,)`` float64::

    0..8   R, world to camera, row major
    9..11  t, mm
    12..16 fx, K[0, 1] (= alpha_c * fx), cx, fy, cy, px
    17..21 k1, k2, p1, p2, k3
    22     |t|_1, mm (scale of the camera-frame coordinates, for error bounds)

Note: numba's on-disk cache does not notice edits of this module in the
kernels that inline it; clear ``__pycache__`` after changing it.

:class:`CompileWatch` tells a face when numba compiles (a kernel not in that
cache yet: the first run after installing, unless ``make warm`` ran), so it can
say why it waits.
"""

from __future__ import annotations

import threading
import time

import numpy as np
from numba import njit
from numba.core import event as _numba_event

N_CP = 23


def pack_camera(camera):
    """One :class:`~organlab.camera.Camera` as a ``(N_CP,)`` float64 vector."""
    cp = np.empty(N_CP)
    cp[0:9] = camera.R.ravel()
    cp[9:12] = camera.t
    K = camera.K
    cp[12], cp[13], cp[14], cp[15], cp[16] = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    cp[17:22] = camera.dist
    cp[22] = np.abs(camera.t).sum()
    return cp


def pack_cameras(cameras):
    """Cameras as a C-contiguous ``(V, N_CP)`` float64 array."""
    return np.ascontiguousarray(np.array([pack_camera(c) for c in cameras], dtype=np.float64).reshape(-1, N_CP))


@njit(cache=True, nogil=True, inline="always")
def to_camera(cp, x, y, z):
    """World point (mm) to the camera frame: ``R @ X + t``."""
    xc = cp[0] * x + cp[1] * y + cp[2] * z + cp[9]
    yc = cp[3] * x + cp[4] * y + cp[5] * z + cp[10]
    zc = cp[6] * x + cp[7] * y + cp[8] * z + cp[11]
    return xc, yc, zc


@njit(cache=True, nogil=True, inline="always")
def to_pixel(cp, xn, yn):
    """Undistorted normalized coordinates ``(X/Z, Y/Z)`` to pixels ``(u, v)``.

    Bouguet's distortion then ``K``, as :func:`organlab.camera.distort` and
    ``Camera._project_cam``.
    """
    k1, k2, p1, p2, k3 = cp[17], cp[18], cp[19], cp[20], cp[21]
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
    return cp[12] * xd + cp[13] * yd + cp[14], cp[15] * yd + cp[16]


@njit(cache=True, nogil=True)
def undistort_points(xd, dist, iterations=30):
    """:func:`organlab.camera.undistort`, compiled: the same Newton steps, term for term, on every point together.

    Each step moves every point, and the steps stop once the largest residual of the step (NaN left out) is below
    1e-14, as there: the same result bit for bit (tests/test_nbcam_undistort.py), some 13x faster on the poses
    check's outlines (700 points a view).

    Parameters
    ----------
    xd : (N, 2) float64
        Distorted normalized coordinates.
    dist : (5,) float64
        ``[k1, k2, p1, p2, k3]``.
    iterations : int
        Maximum number of Newton steps.

    Returns
    -------
    xn : (N, 2) float64
        Undistorted normalized coordinates (a new array).

    Examples
    --------
    >>> import numpy as np
    >>> from organlab.camera import undistort
    >>> xd = np.random.default_rng(0).uniform(-0.4, 0.4, (50, 2))
    >>> dist = np.array([-0.3, 0.1, 0.0012, -0.0008, 0.0])
    >>> bool((undistort_points(xd, dist) == undistort(xd, dist)).all())
    True
    """
    n = xd.shape[0]
    xn = xd.copy()
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    if k1 == 0.0 and k2 == 0.0 and p1 == 0.0 and p2 == 0.0 and k3 == 0.0:
        return xn
    for _ in range(iterations):
        worst = 0.0
        for i in range(n):
            x, y = xn[i, 0], xn[i, 1]
            # organlab.camera.distort
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            res0 = (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)) - xd[i, 0]
            res1 = (y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y) - xd[i, 1]
            # organlab.camera._distort_jacobian
            drad_dr2 = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
            a = radial + x * drad_dr2 * 2 * x + 2 * p1 * y + p2 * (2 * x + 4 * x)
            b = x * drad_dr2 * 2 * y + 2 * p1 * x + p2 * 2 * y
            c = y * drad_dr2 * 2 * x + p1 * 2 * x + 2 * p2 * y
            d = radial + y * drad_dr2 * 2 * y + p1 * (2 * y + 4 * y) + 2 * p2 * x
            det = a * d - b * c
            if abs(det) < 1e-12:
                det = 1e-12
            xn[i, 0] = x - (d * res0 - b * res1) / det
            xn[i, 1] = y - (-c * res0 + a * res1) / det
            e0, e1 = abs(res0), abs(res1)
            if e0 > worst:  # NaN compares False: left out, as np.nanmax
                worst = e0
            if e1 > worst:
                worst = e1
        if worst < 1e-14:
            break
    return xn


class CompileWatch(_numba_event.Listener):
    """Watch numba compile kernels (its cache missed) while registered, in any thread.

    Parameters
    ----------
    on_compile : callable(name), optional
        Called when a kernel starts compiling (not for the kernels it compiles
        inside it), with the kernel's name, in the compiling thread.

    Attributes
    ----------
    count : int
        Kernels compiled (outermost compilations).
    seconds : float
        Wall-clock time spent compiling them, s.

    Examples
    --------
    >>> from numba import njit
    >>> with CompileWatch() as w:
    ...     _ = njit(lambda x: x + 1)(1)
    >>> w.count, w.seconds > 0
    (1, True)
    """

    def __init__(self, on_compile=None):
        self.on_compile = on_compile
        self.count = 0
        self.seconds = 0.0
        self._depth = threading.local()
        self._lock = threading.Lock()

    def on_start(self, event):
        depth = getattr(self._depth, "n", 0)
        self._depth.n = depth + 1
        if depth == 0:
            self._depth.t0 = time.perf_counter()
            with self._lock:
                self.count += 1
            if self.on_compile is not None:
                d = (event.data or {}).get("dispatcher")
                self.on_compile(getattr(getattr(d, "py_func", None), "__name__", "kernel"))

    def on_end(self, event):
        self._depth.n = getattr(self._depth, "n", 1) - 1
        if self._depth.n == 0:
            with self._lock:
                self.seconds += time.perf_counter() - self._depth.t0

    def start(self) -> CompileWatch:
        """Register (numba's ``numba:compile`` events reach :meth:`on_start` / :meth:`on_end`)."""
        _numba_event.register("numba:compile", self)
        return self

    def stop(self) -> None:
        """Unregister (no error when not registered)."""
        try:
            _numba_event.unregister("numba:compile", self)
        except ValueError:
            pass

    def __enter__(self) -> CompileWatch:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
