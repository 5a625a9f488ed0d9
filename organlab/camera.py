"""The one camera model used by every stage of organlab.

A :class:`Camera` is a pinhole camera with Bouguet's (= OpenCV's five
coefficient) lens distortion and skew, placed in the world by its
world-to-camera extrinsics.  Conventions (``session-format.md``):

* lengths in mm, world frame = turntable frame;
* ``x_cam = R @ x_world + t`` (``R`` is ``R_cam_world``), OpenCV camera axes
  (+Z forward, +X right, +Y down);
* ``K = [[fx, alpha_c*fx, cx], [0, fy, cy], [0, 0, 1]]``,
  ``dist = [k1, k2, p1, p2, k3]`` (Bouguet's ``kc``);
* pixel centres are integers, pixels are ``(u, v)`` = (column, row).

The projection follows the thesis's equations (8)-(15) (Bouguet's toolbox):

.. math::

    x_n = (X_c / Z_c, Y_c / Z_c), \\quad r^2 = x^2 + y^2

    x_d = (1 + k_1 r^2 + k_2 r^4 + k_3 r^6)\\, x_n + dx

    dx = (2 p_1 x y + p_2 (r^2 + 2 x^2),\\; p_1 (r^2 + 2 y^2) + 2 p_2 x y)

    u = f_x (x_d + \\alpha_c y_d) + c_x, \\quad v = f_y y_d + c_y
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Camera", "rot_z", "distort", "undistort", "nearest_rotation", "as_points", "ROTATION_TOLERANCE"]

#: Largest ``max |R R^T - I|`` accepted (and re-orthonormalised) by :func:`nearest_rotation`:
#: published pose files print rotations to ~7 digits (|R R^T - I| about 1.5e-6).
ROTATION_TOLERANCE = 1e-4


def rot_z(angle_deg):
    """Rotation matrix about +Z, right-handed.

    Parameters
    ----------
    angle_deg : float
        Angle in degrees.

    Returns
    -------
    R : (3, 3) float64
    """
    a = np.deg2rad(float(angle_deg))
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def nearest_rotation(R, *, tolerance=ROTATION_TOLERANCE):
    """The rotation nearest to an almost orthonormal matrix.

    Parameters
    ----------
    R : (3, 3) float
    tolerance : float
        Largest accepted ``max |R R^T - I|``.

    Returns
    -------
    R_orth : (3, 3) float64
        ``U V^T`` of ``R``'s SVD (the nearest rotation in the Frobenius norm).
    error : float
        ``max |R R^T - I|`` of the input.

    Raises
    ------
    ValueError
        Not 3x3, not finite, ``det R <= 0`` or beyond ``tolerance``; the message
        states the error found.
    """
    R = np.array(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"must be a finite 3x3 matrix, got shape {R.shape}")
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if det <= 0 or err > tolerance:
        raise ValueError(
            f"is not a rotation matrix (max |R R^T - I| = {err:.2g}, det = {det:.7g}; accepted: within "
            f"{tolerance:g} of orthonormal, det > 0)"
        )
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt, err


def as_points(points, name: str = "points") -> np.ndarray:
    """Points as ``(N, 3)`` float64 (one ``(3,)`` point becomes ``(1, 3)``); ValueError naming ``name`` otherwise."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim == 1 and p.shape[0] == 3:
        p = p[None, :]
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {p.shape}")
    return p


def distort(xn, dist):
    """Apply Bouguet/OpenCV distortion to normalized image coordinates.

    Parameters
    ----------
    xn : (N, 2) float64
        Undistorted normalized coordinates ``(X/Z, Y/Z)``.
    dist : (5,) float64
        ``[k1, k2, p1, p2, k3]``.

    Returns
    -------
    xd : (N, 2) float64
        Distorted normalized coordinates.
    """
    k1, k2, p1, p2, k3 = np.asarray(dist, dtype=np.float64)
    x = xn[:, 0]
    y = xn[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def _distort_jacobian(xn, dist):
    k1, k2, p1, p2, k3 = dist
    x = xn[:, 0]
    y = xn[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad_dr2 = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    # d r2 / dx = 2x, d r2 / dy = 2y
    dxd_dx = radial + x * drad_dr2 * 2 * x + 2 * p1 * y + p2 * (2 * x + 4 * x)
    dxd_dy = x * drad_dr2 * 2 * y + 2 * p1 * x + p2 * 2 * y
    dyd_dx = y * drad_dr2 * 2 * x + p1 * 2 * x + 2 * p2 * y
    dyd_dy = radial + y * drad_dr2 * 2 * y + p1 * (2 * y + 4 * y) + 2 * p2 * x
    return dxd_dx, dxd_dy, dyd_dx, dyd_dy


def undistort(xd, dist, *, iterations=30):
    """Invert :func:`distort` by Newton's method.

    Parameters
    ----------
    xd : (N, 2) float64
        Distorted normalized coordinates.
    dist : (5,) float64
        ``[k1, k2, p1, p2, k3]``.
    iterations : int
        Maximum number of Newton steps (it stops earlier once converged).

    Returns
    -------
    xn : (N, 2) float64
        Undistorted normalized coordinates, ``distort(xn) == xd`` to about
        1e-12 inside the image of any physically plausible lens.
    """
    dist = np.asarray(dist, dtype=np.float64)
    xd = np.asarray(xd, dtype=np.float64)
    xn = xd.copy()
    if not np.any(dist):
        return xn
    for _ in range(iterations):
        res = distort(xn, dist) - xd
        a, b, c, d = _distort_jacobian(xn, dist)
        det = a * d - b * c
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        step_x = (d * res[:, 0] - b * res[:, 1]) / det
        step_y = (-c * res[:, 0] + a * res[:, 1]) / det
        xn[:, 0] -= step_x
        xn[:, 1] -= step_y
        if np.nanmax(np.abs(res), initial=0.0) < 1e-14:
            break
    return xn


@dataclass(frozen=True, eq=False)
class Camera:
    """A calibrated, posed camera: pinhole + Bouguet distortion + skew.

    Parameters
    ----------
    K : (3, 3) float64
        Intrinsic matrix ``[[fx, alpha_c*fx, cx], [0, fy, cy], [0, 0, 1]]``, px.
    dist : (5,) float64
        Distortion ``[k1, k2, p1, p2, k3]`` (Bouguet's ``kc``).
    R : (3, 3) float64
        Rotation world to camera (``R_cam_world``).
    t : (3,) float64
        Translation world to camera, mm: ``x_cam = R @ x_world + t``.
    image_size : (2,) int
        ``(width, height)`` in pixels.
    """

    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray = None
    t: np.ndarray = None
    image_size: tuple = (640, 480)

    def __post_init__(self):
        K = np.array(self.K, dtype=np.float64)
        for name, value in (("K", K), ("dist", self.dist), ("R", self.R), ("t", self.t)):
            if value is not None and not np.all(np.isfinite(np.asarray(value, dtype=np.float64))):
                raise ValueError(f"{name} must hold finite numbers, got {np.asarray(value).tolist()}")
        if K.shape != (3, 3) or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise ValueError(f"K must be an upper-triangular 3x3 matrix with last row [0, 0, 1], got {K.tolist()}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"K must have positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}")
        dist = np.zeros(5) if self.dist is None else np.array(self.dist, dtype=np.float64).ravel()
        if dist.shape == (4,):
            dist = np.append(dist, 0.0)
        if dist.shape != (5,):
            raise ValueError(f"dist must hold 5 coefficients [k1, k2, p1, p2, k3], got {dist.shape[0]}")
        R = np.eye(3) if self.R is None else np.array(self.R, dtype=np.float64)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("R must be a 3x3 rotation matrix (orthonormal, det +1)")
        t = np.zeros(3) if self.t is None else np.array(self.t, dtype=np.float64).ravel()
        if t.shape != (3,):
            raise ValueError(f"t must have 3 elements, got {t.shape}")
        size = tuple(int(s) for s in self.image_size)
        if len(size) != 2 or min(size) <= 0:
            raise ValueError(f"image_size must be (width, height) > 0, got {self.image_size}")
        for name, value in (("K", K), ("dist", dist), ("R", R), ("t", t)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "image_size", size)

    # ------------------------------------------------------------------ props
    @property
    def width(self) -> int:
        return self.image_size[0]

    @property
    def height(self) -> int:
        return self.image_size[1]

    @property
    def skew(self) -> float:
        """``alpha_c``: the skew coefficient (``K[0, 1] / K[0, 0]``)."""
        return self.K[0, 1] / self.K[0, 0]

    @property
    def center(self) -> np.ndarray:
        """Camera centre in the world frame, mm, ``(3,)``."""
        return -self.R.T @ self.t

    @property
    def rvec(self) -> np.ndarray:
        """Rodrigues vector of ``R`` (as OpenCV's ``rvec``)."""
        import cv2

        return cv2.Rodrigues(self.R)[0].ravel()

    def pixel_footprint(self, point: np.ndarray) -> float:
        """Size of one pixel at a world point, mm: its depth over the mean focal length.

        Parameters
        ----------
        point : (3,) float64, mm, world frame

        Returns
        -------
        float, mm (inf for a point on or behind the camera plane)
        """
        z = float(self.world_to_camera(np.asarray(point, np.float64).reshape(1, 3))[0, 2])
        return z / (0.5 * (self.K[0, 0] + self.K[1, 1])) if z > 0 else float("inf")

    # ------------------------------------------------------------- transforms
    def with_pose(self, R: np.ndarray, t: np.ndarray) -> Camera:
        """Same intrinsics, new world-to-camera pose."""
        return Camera(self.K, self.dist, R, t, self.image_size)

    def at_table_angle(self, angle_deg: float) -> Camera:
        """The camera seeing the turntable rotated by ``angle_deg``.

        ``self`` is the camera at table angle 0 (``R_cam``, ``t_cam``); a point
        fixed on the table at ``X`` is at ``Rz(angle) @ X`` so the view's pose
        is ``R = R_cam @ Rz(angle)``, ``t = t_cam`` (session format).
        """
        return self.with_pose(self.R @ rot_z(angle_deg), self.t)

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """Map world points to the camera frame.

        Parameters
        ----------
        points : (N, 3) float64, mm, world frame

        Returns
        -------
        (N, 3) float64, mm, camera frame
        """
        p = as_points(points)
        return p @ self.R.T + self.t

    # ------------------------------------------------------------- projection
    def project(self, points: np.ndarray, *, return_depth: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Project world points to pixels through the full camera model.

        Parameters
        ----------
        points : (N, 3) float64, mm, world frame
        return_depth : bool
            Also return the camera-frame depth ``Z_c`` of every point.

        Returns
        -------
        pixels : (N, 2) float64
            ``(u, v)``; NaN for points on or behind the camera plane
            (``Z_c <= 0``), which no image can show.
        depth : (N,) float64, mm
            Only with ``return_depth``.
        """
        pc = self.world_to_camera(points)
        uv, z = self._project_cam(pc)
        return (uv, z) if return_depth else uv

    def _project_cam(self, pc):
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            front = z > 0
            zs = np.where(front, z, np.nan)
            xn = pc[:, :2] / zs[:, None]
        xd = distort(xn, self.dist)
        K = self.K
        u = K[0, 0] * xd[:, 0] + K[0, 1] * xd[:, 1] + K[0, 2]
        v = K[1, 1] * xd[:, 1] + K[1, 2]
        return np.stack([u, v], axis=1), z

    def pixels_to_normalized(self, pixels: np.ndarray) -> np.ndarray:
        """Undistorted normalized coordinates ``(X/Z, Y/Z)`` of pixels.

        Parameters
        ----------
        pixels : (N, 2) float64, ``(u, v)``

        Returns
        -------
        (N, 2) float64
        """
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        K = self.K
        yd = (px[:, 1] - K[1, 2]) / K[1, 1]
        xd = (px[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
        return undistort(np.stack([xd, yd], axis=1), self.dist)

    def rays(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Back-project pixels to rays in the world frame.

        Parameters
        ----------
        pixels : (N, 2) float64, ``(u, v)``

        Returns
        -------
        origins : (N, 3) float64, mm, world frame
            The camera centre, repeated.
        directions : (N, 3) float64, unit vectors, world frame
        """
        xn = self.pixels_to_normalized(pixels)
        d_cam = np.concatenate([xn, np.ones((xn.shape[0], 1))], axis=1)
        d = d_cam @ self.R  # R.T @ d_cam for each row
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        origins = np.broadcast_to(self.center, d.shape).copy()
        return origins, d

    # -------------------------------------------------------------- serialise
    def intrinsics_dict(self) -> dict:
        return {"K": self.K.tolist(), "dist": self.dist.tolist(), "image_size": list(self.image_size)}

    def to_dict(self) -> dict:
        """JSON-ready dict: ``K``, ``dist``, ``R``, ``t``, ``image_size``."""
        d = self.intrinsics_dict()
        d.update(R=self.R.tolist(), t=self.t.tolist())
        return d

    @classmethod
    def from_dict(cls, d: dict, *, image_size: tuple[int, int] | None = None) -> Camera:
        """Build from a dict with ``K``, ``dist`` and optional ``R``, ``t``, ``image_size``."""
        size = d.get("image_size", image_size)
        if size is None:
            raise ValueError("image_size is needed")
        return cls(d["K"], d.get("dist"), d.get("R"), d.get("t"), tuple(size))

    def __repr__(self):
        fx, fy = self.K[0, 0], self.K[1, 1]
        return (
            f"Camera(fx={fx:.2f}, fy={fy:.2f}, cx={self.K[0, 2]:.2f}, cy={self.K[1, 2]:.2f}, "
            f"skew={self.skew:.3g}, dist={np.round(self.dist, 5).tolist()}, "
            f"center_mm={np.round(self.center, 2).tolist()}, image_size={self.image_size})"
        )
