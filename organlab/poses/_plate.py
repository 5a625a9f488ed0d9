"""The camera's distance to the table axis and its height, measured on the turntable plate's rim.

Silhouettes under circular motion leave the camera's distance to the axis and its height
unseen (a scale about the axis and a shift along it change no silhouette, docs/trust.md).
The plate is a circle of known radius on the axis, seen in the frames of the empty scene
(taken with the camera where it was for the views): under the known intrinsics and the
camera's orientation relative to the axis (which the silhouettes do fix), its rim's image
fixes the two.

Method: the rim circle (radius ``R`` at height ``z``, world frame) is projected through the
full camera model (distortion included) at 720 points; at each, the image's intensity profile
across the projected rim (along its normal, bilinear, 1/8 px steps) locates the edge at the
centroid of the intensity step (the plate's top against the backdrop on the far side, against
the plate's side wall on the near side; a drop or a rise, whichever is stronger).  Points whose profile
would reach the side wall's lower edge or leave the image are not used.  The camera's centre
``C`` is moved within the unseen family ``C -> s C + h e_z`` (rotation kept) to minimise the
edges' offsets along the normals (Gauss-Newton, robust re-weighting; the edges re-measured at
each step).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ._model import _rotvecs, _rz_stack, robust_lm

#: Points along the rim.
N_RIM = 720
#: Half-length of the intensity profile across the rim, px (shortened where the side wall is thin).
HALF_PX = 3.0
#: Profile step, px.
STEP_PX = 0.125
#: Fewest rim points with a usable edge.
MIN_POINTS = 60


@dataclass
class PlateFit:
    """What :func:`fit_plate` measured.

    ``scale`` and ``height_mm`` map the camera's centre ``C -> scale * C + height_mm * e_z``, ``pitch_rad``
    turns it about its own X axis (when fitted);
    ``rms_px`` the edges' RMS offset from the fitted rim, ``n_points`` the rim points used.
    """

    scale: float
    height_mm: float
    rms_px: float
    n_points: int
    sd_scale: float
    sd_height_mm: float
    pitch_rad: float = 0.0


def _grey(image):
    img = np.asarray(image, dtype=np.float64)
    return img.mean(axis=2) if img.ndim == 3 else img


def _rim_geometry(camera, radius, z, wall_mm, n=N_RIM):
    """Projected rim points ``(n, 2)``, outward unit normals ``(n, 2)`` and the side wall's lower edge's
    offset along them, px (``nan`` where the wall is not seen below the rim)."""
    th = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    c, s = np.cos(th), np.sin(th)
    ring = lambda r, zz: np.stack([r * c, r * s, np.full(n, zz)], axis=1)  # noqa: E731
    ring_at = lambda t, r, zz: np.stack([r * np.cos(t), r * np.sin(t), np.full(n, zz)], axis=1)  # noqa: E731
    p = camera.project(ring(radius, z))
    # the normal of the projected rim (perpendicular to its image), pointing outward: the image of the radial
    # direction is oblique to it (44 degrees at 45 degrees round the rim under a 25 degree elevation), and an
    # offset measured along an oblique direction changes when the rim's points slide along it, i.e. under a turn
    # of the camera about the axis, which no image shows
    tang = camera.project(ring_at(th + 1e-4, radius, z)) - camera.project(ring_at(th - 1e-4, radius, z))
    nrm = np.stack([tang[:, 1], -tang[:, 0]], axis=1)
    nrm *= np.sign(np.einsum("ij,ij->i", nrm, camera.project(ring(radius + 0.5, z)) - p))[:, None]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    low = camera.project(ring(radius, z - wall_mm))
    gap = np.einsum("ij,ij->i", low - p, nrm)
    # the wall is seen where it faces the camera
    faces = (camera.center[0] * c + camera.center[1] * s) > radius
    gap = np.where(faces, gap, np.nan)
    return p, nrm, gap


def _edges(grey, p, nrm, gap, half_px=HALF_PX, local_px=None):
    """Edge offsets along the normals, px (``nan`` where no clean edge): the strongest step within
    ``+-half_px``, located at the centroid of its gradient (within ``local_px`` of its peak, when given:
    the coarse search, where the plate's rings or the side wall's lower edge may be in the window)."""
    from scipy.ndimage import map_coordinates

    h, w = grey.shape
    half = np.full(len(p), float(half_px))
    near = np.isfinite(gap)
    half[near] = np.minimum(half_px, 0.5 * gap[near] - 0.75)
    ok = half >= 1.25
    offs = np.arange(-half_px, half_px + 1e-9, STEP_PX)
    pts = p[:, None, :] + offs[None, :, None] * nrm[:, None, :]
    inside = (pts[..., 0] >= 1) & (pts[..., 0] <= w - 2) & (pts[..., 1] >= 1) & (pts[..., 1] <= h - 2)
    window = np.abs(offs)[None, :] <= half[:, None]
    use = window & inside
    ok &= np.isfinite(p).all(1) & (use.sum(1) == window.sum(1))
    prof = map_coordinates(grey, [np.nan_to_num(pts[..., 1]).ravel(), np.nan_to_num(pts[..., 0]).ravel()],
                           order=1, mode="nearest").reshape(pts.shape[:2])
    drop = -np.gradient(prof, STEP_PX, axis=1)
    drop = np.where(use, drop, 0.0)
    # a plate darker than what lies beyond its rim: the edge is a rise
    rise = (-drop).max(axis=1) > drop.max(axis=1)
    drop[rise] = -drop[rise]
    k = drop.argmax(axis=1)
    peak = drop[np.arange(len(p)), k]
    local = np.abs(offs[None, :] - offs[k][:, None]) <= (np.inf if local_px is None else local_px)
    wgt = np.where(local & (drop > 0.25 * peak[:, None]), drop, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        o = (wgt * offs[None, :]).sum(1) / wgt.sum(1)
    # a clean step, well away from the window's ends
    ok &= peak * STEP_PX > 2.0
    ok &= np.abs(o) < half - 1.0
    return np.where(ok, o, np.nan)


def _camera_at(camera, scale, height, pitch=0.0):
    """``camera`` with its centre ``C -> scale C + height e_z`` and turned by ``pitch`` (rad) about its own X axis."""
    c, s = np.cos(pitch), np.sin(pitch)
    R = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]) @ camera.R
    C = scale * camera.center + np.array([0.0, 0.0, height])
    return camera.with_pose(R, -R @ C)


def fit_plate(camera: Camera, image: np.ndarray, *, radius_mm: float, top_mm: float = 0.0, wall_mm: float = 10.0,
              iterations: int = 6, pitch: bool = False, half_px: float = HALF_PX, local_px: float | None = None) -> PlateFit | None:
    """Fit the camera's distance to the table axis and its height to the plate's rim in ``image``.

    Parameters
    ----------
    camera : Camera
        The camera (table angle 0, world = table frame) whose orientation is trusted.
    image : (H, W) or (H, W, 3) array
        The empty scene (e.g. the background model).
    radius_mm, top_mm : float
        The plate's radius and the height of its top face, world frame, mm.
    wall_mm : float
        How far below the top the side wall's lower edge is assumed at least (only limits the profiles).
    pitch : bool
        Also turn the camera about its own X axis (its tilt toward the table), ``PlateFit.pitch_rad``.
    half_px, local_px : float
        The edge search's half-width across the rim, and the step's extent about its peak (coarse search).

    Returns
    -------
    PlateFit or None
        None when too few rim points show a clean edge.
    """
    grey = _grey(image)
    q = np.zeros(3)  # scale - 1, height, pitch
    n_q = 3 if pitch else 2
    sd = np.full(3, np.nan)
    steps = (1e-4, 0.05, 1e-5)
    rms, m = np.nan, np.zeros(0, bool)
    for it in range(iterations):
        cam = _camera_at(camera, 1 + q[0], q[1], q[2])
        p, nrm, gap = _rim_geometry(cam, radius_mm, top_mm, wall_mm)
        o = _edges(grey, p, nrm, gap, half_px, local_px)
        m = np.isfinite(o)
        if m.sum() < MIN_POINTS:
            return None
        # Jacobian of the projected rim along the normals
        J = np.empty((len(p), n_q))
        for k in range(n_q):
            qk = q.copy()
            qk[k] += steps[k]
            pp, _, _ = _rim_geometry(_camera_at(camera, 1 + qk[0], qk[1], qk[2]), radius_mm, top_mm, wall_mm)
            J[:, k] = np.einsum("ij,ij->i", pp - p, nrm) / steps[k]
        r = o[m]
        Jm = J[m]
        med = np.median(r)
        mad = 1.4826 * np.median(np.abs(r - med)) + 1e-3
        wts = 1.0 / np.maximum(1.0, np.abs(r - med) / (3 * mad))  # Huber-like
        A = Jm * wts[:, None]
        step, *_ = np.linalg.lstsq(A, r * wts, rcond=None)
        q[:n_q] += step
        res = r - Jm @ step
        rms = float(np.sqrt(np.mean((res * wts) ** 2)))
        sd[:n_q] = np.sqrt(np.diag(np.linalg.inv(A.T @ A) * rms**2))
        if abs(step[0]) < 1e-6 and abs(step[1]) < 1e-4:
            break
    return PlateFit(scale=float(1 + q[0]), height_mm=float(q[1]), rms_px=rms, n_points=int(m.sum()),
                    sd_scale=float(sd[0]), sd_height_mm=float(sd[1]), pitch_rad=float(q[2]))


# ------------------------------------------------------------------ the rim in the pose fit
#: The rim edges' offsets are divided by this (px) in the joint fit with the tangents: their RMS about
#: the true rim on the renders (0.11 px at 320 x 240).
SIGMA_RIM_PX = 0.25


@dataclass
class Rim:
    """Edge points measured on the plate's rim: rim angles (rad), image points ``(m, 2)`` and the
    projected rim's outward normals ``(m, 2)`` where they were measured."""

    theta: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    radius: float
    top: float

    def residuals(self, camera):
        """Offsets (px) of the measured edges from ``camera``'s projection of the rim, along the normals."""
        c, s = np.cos(self.theta), np.sin(self.theta)
        X = np.stack([self.radius * c, self.radius * s, np.full(len(c), self.top)], axis=1)
        return np.einsum("ij,ij->i", self.points - camera.project(X), self.normals)


def measure_rim(camera, image, *, radius_mm, top_mm=0.0, wall_mm=10.0):
    """The rim's edge points in ``image``, looked for across ``camera``'s projection of it (None: too few)."""
    grey = _grey(image)
    th = np.linspace(0.0, 2 * np.pi, N_RIM, endpoint=False)
    p, nrm, gap = _rim_geometry(camera, radius_mm, top_mm, wall_mm)
    o = _edges(grey, p, nrm, gap)
    m = np.isfinite(o)
    if m.sum() < MIN_POINTS:
        return None
    return Rim(th[m], p[m] + o[m, None] * nrm[m], nrm[m], float(radius_mm), float(top_mm))


def _x_for_camera(model, x, cam):
    """``x`` with the shared pose set so that view 0's camera is ``cam`` (the views' angles kept)."""
    from scipy.spatial.transform import Rotation


    _, _, d, _ = model.split(x)
    Rc = cam.R @ _rz_stack([model.angles[0] + d[0]])[0].T
    w = Rotation.from_matrix(Rc @ model.base.R.T).as_rotvec()
    x = x.copy()
    x[:3] = w
    x[3:6] = cam.t - _rotvecs(w[None])[0] @ model.base.t
    return x


def fit_with_rim(problem, model, x, template, image, *, radius_mm, top_mm=0.0, rounds=3):
    """Refit the tangents' problem with the plate's rim (seen by view 0's camera in ``image``) added.

    The rim's residuals depend on the shared camera pose only (the first 6 parameters).  The edges are
    re-measured at the camera of each round.  Returns ``(x, rim_rms_px, n_points)`` or ``None`` when the
    rim is not found.
    """
    ns = model.n_shared

    def cam_of(xx):
        R, t = model.poses(xx)
        return template.with_pose(R[0], t[0])

    # come close first, on the rim alone: the unseen scale and height and the camera's tilt (which the
    # silhouettes of a near-symmetric specimen pin least), a coarse search (+-8 px) then the fine one
    cam = cam_of(x)
    for half, local in ((8.0, 1.5), (HALF_PX, None)):
        f = fit_plate(cam, image, radius_mm=radius_mm, top_mm=top_mm, pitch=True, half_px=half, local_px=local)
        if f is None:
            return None
        cam = _camera_at(cam, f.scale, f.height_mm, f.pitch_rad)
    x = _x_for_camera(model, x, cam)
    rim = None
    for _ in range(rounds):
        rim = measure_rim(cam_of(x), image, radius_mm=radius_mm, top_mm=top_mm)
        if rim is None:
            return None

        def fun(xx, rim=rim):
            return np.concatenate([problem.residuals(xx), rim.residuals(cam_of(xx)) / SIGMA_RIM_PX])

        def jac(xx, rim=rim):
            J0 = problem.jacobian(xx)
            Jr = np.zeros((len(rim.theta), len(xx)))
            r0 = rim.residuals(cam_of(xx))
            for k in range(ns):
                h = 1e-6 if k < 3 else 1e-4
                xk = xx.copy()
                xk[k] += h
                Jr[:, k] = (rim.residuals(cam_of(xk)) - r0) / h / SIGMA_RIM_PX
            return np.vstack([J0, Jr])

        x, _ = robust_lm(fun, jac, x)
    r = rim.residuals(cam_of(x))
    return x, float(np.sqrt(np.mean(r**2))), len(r)
