"""The pose model refined from the silhouettes, and its least-squares fit.

Turntable model (views posed by the turntable calibration)::

    R_i = Exp(w) R_cam Rz(a_i + d_i) [Rz(psi)]      t_i = Exp(w) t_cam + tau [+ R_i' s]

``w`` (3, rad, camera frame: a rotation about the camera's centre) and ``tau``
(3, mm, camera frame: a move of the centre) are shared by every view; ``d_i``
(degrees) is view ``i``'s table-angle correction (``d_0 = 0``: the first view
fixes the specimen's orientation on the plate, which silhouettes cannot see);
for views from a slip on, the specimen has moved on the plate by ``Rz(psi)``
and ``s = (sx, sy, 0)`` (bracketed terms; ``R_i'`` is ``R_i`` without
``Rz(psi)``).

Posed model (views whose poses were given, e.g. published cameras): each view
is turned about the axis of the ring its camera centres lie on by ``d_i``.

Priors (residuals in units of their standard deviation): ``d_i`` near 0
(:data:`SIGMA_ANGLE_DEG`), a smooth trend (:data:`SIGMA_TREND_DEG`) plus each
stop's own error (:data:`SIGMA_JITTER_DEG`, :func:`trend_jitter_root`), the shared pose near the board calibration's
(:data:`SIGMA_ROTATION_DEG`, :data:`SIGMA_TRANSLATION_MM`): the last also pins
what silhouettes cannot see (the camera's move along the table axis and toward
it: both only move or scale the model).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np

from ..camera import Camera
from ._tangents import MAX_HALF_ANGLE_DEG, pair_angle_derivatives, pair_angles

#: Each view's angle correction, held loosely (its drift is what the tangents measure): a tight hold pulls
#: a drifting table's angles back toward the commanded ones, by a turn common to every view but the first
#: (3 degrees: 0.2-0.34 degrees on the drifting ``dented`` table at 640 x 480, docs/trust.md).
SIGMA_ANGLE_DEG = 30.0
#: The angle corrections are a trend (a table losing steps drifts smoothly over the turn) plus each stop's own
#: positioning error, independent from stop to stop.  The trend's second differences have this sd (a slope that
#: changes by 0.05 degrees per stop: far more curved than the linear drift of lost steps) ...
SIGMA_TREND_DEG = 0.05
#: ... each stop's own error this sd (the rigs of issue 20: 0.3 degrees of jitter per stop).  Until 2026-12-03 the
#: second differences of the corrections themselves had sd 0.5 (one prior for both): a stop's own error then
#: costs 6 second differences' worth and pulls its neighbours along, so a real jitter step was smoothed away
#: (``driftb_br11`` view 27, 0.53 degrees off; docs/trust.md).
SIGMA_JITTER_DEG = 0.3
#: The angles are first fitted with the stops' own errors held to this sd (the trend alone, nearly), then freed
#: to :data:`SIGMA_JITTER_DEG` from there: freed at once from the commanded angles, views whose outlines change
#: fastest with their angle (15, 33 of ``drift_br11``) stop in local minima 0.8 degrees off.
SIGMA_JITTER_START_DEG = 0.05
#: The capture's angle audit (measured from the board at every stop): its error on the simulated rig is
#: below 0.01 deg at 640 x 480, 0.05 deg at 320 x 240 (docs/capture.md); the views are taken at the same stops
#: in a later pass, so a little more.
SIGMA_AUDIT_DEG = 0.1
SIGMA_ROTATION_DEG = 1.0
#: About the camera's X axis (its tilt toward the table): the silhouettes of a specimen
#: near symmetric about the axis pin it least (it trades with the model's height and shape).
SIGMA_PITCH_DEG = 0.25
#: Weight of the tangents that touch a silhouette's foot on the plate in the views' tangent RMS that 'auto' reads
#: (:data:`._refine.FLAG_SUBPIXEL_PX` was measured without them: before the sub-pixel outlines they were the least
#: reliable, 0.25 px against 0.14).  The fits weigh them by their measured noise (:func:`._refine._foot_weight`).
FOOT_WEIGHT = 0.0
SIGMA_TRANSLATION_MM = 2.0
SIGMA_SLIP_MM = 5.0
SIGMA_SLIP_DEG = 5.0
#: Tangent residuals are divided by this (px): their noise on clean renders.
SIGMA_PX = 0.25
#: soft-L1 scale, in SIGMA_PX: a pair a moved view spoils weighs little.
F_SCALE = 3.0


def _rotvecs(w):
    """(n, 3) rotation vectors (rad) to (n, 3, 3) matrices."""
    w = np.atleast_2d(w)
    th = np.linalg.norm(w, axis=1)
    k = w / np.where(th < 1e-15, 1.0, th)[:, None]
    Kx = np.zeros((len(w), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3) + s * Kx + (1 - c) * Kx @ Kx


def _rz_stack(deg):
    a = np.deg2rad(np.asarray(deg, np.float64))
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((len(a), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def _axis_rot(axis, deg):
    """(n, 3, 3) rotations about a unit axis by angles in degrees."""
    return _rotvecs(np.outer(np.deg2rad(np.asarray(deg, np.float64)), axis))


@dataclass
class Model:
    """Parameter layout and the cameras it gives.

    ``kind`` is ``'turntable'`` (``base`` = the camera at table angle 0,
    ``angles`` the views' table angles) or ``'posed'`` (``posed`` = the given
    cameras, ``axis``/``axis_point`` the ring's axis).
    """

    kind: str
    n: int
    angles: np.ndarray
    base: Camera | None = None
    posed: list | None = None
    axis: np.ndarray | None = None
    axis_point: np.ndarray | None = None
    slip_view: int | None = None
    shared: bool = True
    angles_free: bool = True
    #: measured angle corrections (the capture's angle audit, degrees; NaN: not audited), or None
    audit_deg: np.ndarray | None = None
    #: sd of each stop's own angle error, degrees (None: :data:`SIGMA_JITTER_DEG`)
    jitter_deg: float | None = None

    @property
    def n_shared(self):
        return 6 if (self.kind == "turntable" and self.shared) else 0

    @property
    def n_params(self):
        return self.n_shared + (self.n - 1) + (3 if self.slip_view is not None else 0)

    def start(self):
        """The parameters to start from: the calibrated poses, each angle at its prior mean (the audit's)."""
        x = np.zeros(self.n_params)
        ns = self.n_shared
        x[ns : ns + self.n - 1] = self.angle_prior()[0][1:]
        return x

    def split(self, x):
        """``(w, tau, d (n,), slip (3,) or None)``; with ``x`` of shape ``(..., n_params)`` each gets those leading axes."""
        x = np.asarray(x, np.float64)
        ns = self.n_shared
        lead = x.shape[:-1]
        w = x[..., :3] if ns else np.zeros(lead + (3,))
        tau = x[..., 3:6] if ns else np.zeros(lead + (3,))
        d = np.concatenate([np.zeros(lead + (1,)), x[..., ns : ns + self.n - 1]], axis=-1)
        slip = x[..., ns + self.n - 1 :] if self.slip_view is not None else None
        return w, tau, d, slip

    def poses(self, x):
        """``R (n, 3, 3)``, ``t (n, 3)`` of every view under parameters ``x``.

        ``x`` may have leading axes (``(..., n_params)``: many parameter vectors at once); ``R`` and ``t`` get them too.
        """
        x = np.asarray(x, np.float64)
        lead = x.shape[:-1]
        w, tau, d, slip = self.split(x.reshape(-1, x.shape[-1]))
        B, n = len(d), self.n
        if self.kind == "turntable":
            Rw = _rotvecs(w)
            Rc = Rw @ self.base.R
            tc = Rw @ self.base.t + tau
            R = Rc[:, None] @ _rz_stack((self.angles + d).ravel()).reshape(B, n, 3, 3)
            t = np.broadcast_to(tc[:, None], (B, n, 3)).copy()
        else:
            Q = _axis_rot(self.axis, d.ravel()).reshape(B, n, 3, 3)
            c = self.axis_point
            R0 = np.stack([cam.R for cam in self.posed])
            t0 = np.stack([cam.t for cam in self.posed])
            R = R0 @ Q
            t = np.einsum("nab,Bnb->Bna", R0, c - np.einsum("Bnab,b->Bna", Q, c)) + t0
        if slip is not None:
            k = self.slip_view
            Rs = _rz_stack(slip[:, 2])
            s = np.zeros((B, 3))
            s[:, :2] = slip[:, :2]
            t[:, k:] = np.einsum("Bnab,Bb->Bna", R[:, k:], s) + t[:, k:]
            R[:, k:] = R[:, k:] @ Rs[:, None]
        return R.reshape(lead + (n, 3, 3)), t.reshape(lead + (n, 3))

    def cameras(self, x, template):
        R, t = self.poses(x)
        return [template.with_pose(R[i], t[i]) for i in range(self.n)]

    def angle_prior(self):
        """Prior mean and sd of every view's angle correction, degrees: the audit's where measured."""
        if self.audit_deg is None:
            return np.zeros(self.n), np.full(self.n, SIGMA_ANGLE_DEG)
        a = np.asarray(self.audit_deg, np.float64)
        has = np.isfinite(a)
        ref = a[0] if has[0] else 0.0  # the first view fixes the orientation: corrections relative to it
        m = np.where(has, a - ref, 0.0)
        sd = np.where(has, SIGMA_AUDIT_DEG, SIGMA_ANGLE_DEG)
        return m, sd

    def prior(self, x):
        """Prior residuals (units of their sigma)."""
        w, tau, d, slip = self.split(x)
        m, sd = self.angle_prior()
        out = [(d[1:] - m[1:]) / (sd[1:] if self.angles_free else 1e-4)]
        if self.kind == "turntable" and self.n >= 3:
            e = d - m  # what the audit did not measure: a trend plus each stop's own error
            out.append(trend_jitter_root(self.n, SIGMA_TREND_DEG, self.jitter_deg or SIGMA_JITTER_DEG) @ e)
        if self.n_shared:
            out.append(np.rad2deg(w) / np.array([SIGMA_PITCH_DEG, SIGMA_ROTATION_DEG, SIGMA_ROTATION_DEG]))
            out.append(tau / SIGMA_TRANSLATION_MM)
        if slip is not None:
            out.append(slip[:2] / SIGMA_SLIP_MM)
            out.append(slip[2:] / SIGMA_SLIP_DEG)
        return np.concatenate(out)


@functools.lru_cache(maxsize=16)
def trend_jitter_root(n: int, trend_deg: float, jitter_deg: float) -> np.ndarray:
    """The prior of ``n`` angle corrections that are a trend plus each stop's own error, as residuals.

    ``e = s + j``: ``s`` a trend whose second differences have sd ``trend_deg``, ``j`` independent errors of sd
    ``jitter_deg``.  Integrating ``s`` out, ``e`` has the precision ``P = q (I - (I + Q_s / q)^-1)`` (``q =
    jitter_deg^-2``, ``Q_s = D2' D2 / trend_deg^2``); a linear trend costs nothing.

    Returns
    -------
    S : (n, n) float64
        ``|S e|^2 = e' P e`` (``S`` = ``sqrt(Lambda) V'`` of ``P``'s eigendecomposition).

    Examples
    --------
    >>> import numpy as np
    >>> S = trend_jitter_root(36, 0.05, 0.3)
    >>> float(np.sum((S @ np.linspace(0.0, 3.0, 36)) ** 2)) < 1e-9    # a linear drift is free
    True
    >>> e = np.zeros(36); e[10] = 0.3                                   # one stop 1 sd off (the trend takes a little)
    >>> round(float(np.sum((S @ e) ** 2)), 2)
    0.85
    """
    D = np.diff(np.eye(n), 2, axis=0)
    q = 1.0 / jitter_deg**2
    P = q * (np.eye(n) - np.linalg.inv(np.eye(n) + D.T @ D / (trend_deg**2 * q)))
    lam, V = np.linalg.eigh(0.5 * (P + P.T))
    return np.sqrt(np.clip(lam, 0.0, None))[:, None] * V.T


class Problem:
    """Tangent residuals of every usable pair under a :class:`Model`."""

    def __init__(self, model, rays_cam, centroid_cam, f_px, *, pairs=None, x0=None, low=None, foot_weight=None):
        self.model = model
        self.rays_cam = rays_cam  # (n, M, 3)
        self.centroid_cam = centroid_cam  # (n, 3)
        self.f = float(f_px)
        x0 = np.zeros(model.n_params) if x0 is None else x0
        if pairs is None:
            pairs = self._usable_pairs(x0)
        self.I, self.J = pairs
        self.scale = self._scale(x0)
        # tangents that touch a silhouette's foot (where it meets the plate: shadows) weigh foot_weight
        # (default FOOT_WEIGHT), decided once at the starting poses; ``foot`` marks them
        self.keep = np.ones((len(self.I), 2))
        self.foot = np.zeros((len(self.I), 2), dtype=bool)
        self.foot_weight = FOOT_WEIGHT if foot_weight is None else float(foot_weight)
        if low is not None:
            rays_w, C, cen_w = self._geometry(x0)
            _, _, _, idx = pair_angles(rays_w, C, cen_w, self.I, self.J, return_index=True)
            li, lj = low[self.I], low[self.J]
            P = np.arange(len(self.I))
            for side in (0, 1):
                bad = li[P, idx[:, side]] | lj[P, idx[:, 2 + side]]
                self.foot[bad, side] = True
                self.keep[bad, side] = self.foot_weight
        self.by_view = [np.nonzero((self.I == v) | (self.J == v))[0] for v in range(model.n)]

    def _geometry(self, x):
        R, t = self.model.poses(x)
        C = -np.einsum("nba,nb->na", R, t)
        rays_w = self.rays_cam @ R  # (n, M, 3) @ (n, 3, 3): each ray r turned to R' r
        cen_w = np.einsum("nk,nkl->nl", self.centroid_cam, R)
        return rays_w, C, cen_w

    def _usable_pairs(self, x):
        n = self.model.n
        I, J = np.triu_indices(n, 1)
        rays_w, C, cen_w = self._geometry(x)
        # no baseline, no epipolar planes: two views at one pose (e.g. a view labelled with another's angle)
        apart = np.linalg.norm(C[J] - C[I], axis=1) > 1e-3 * np.linalg.norm(C, axis=1).mean()
        I, J = I[apart], J[apart]
        psi, si, sj = pair_angles(rays_w, C, cen_w, I, J)
        lim = np.deg2rad(MAX_HALF_ANGLE_DEG)
        ok = (np.abs(psi).max(axis=1) < lim) & (si > 0.2) & (sj > 0.2)
        return I[ok], J[ok]

    def _scale(self, x):
        rays_w, C, cen_w = self._geometry(x)
        _, si, sj = pair_angles(rays_w, C, cen_w, self.I, self.J)
        return self.f * 0.5 * (si + sj)

    def pair_residuals(self, x, sel=None):
        """``(P, 2)`` px: the extremal planes of view ``i`` minus view ``j``'s."""
        I, J = (self.I, self.J) if sel is None else (self.I[sel], self.J[sel])
        geometry = self._geometry(x)
        psi, _, _, idx = pair_angles(*geometry, I, J, return_index=True)
        if sel is None:  # the Jacobian at this x (robust_lm's next call) reuses the extremal rays
            self._extremal = (self.model, np.array(x, np.float64), geometry, idx)
        sc = self.scale if sel is None else self.scale[sel]
        kp = self.keep if sel is None else self.keep[sel]
        return (psi[:, :2] - psi[:, 2:]) * sc[:, None] * kp

    def _extremal_rays(self, x):
        """:meth:`_geometry` at ``x`` and each pair's extremal rays (``index`` of :func:`pair_angles`)."""
        got = getattr(self, "_extremal", None)
        if got is not None and got[0] is self.model and np.array_equal(got[1], x):
            return got[2], got[3]
        geometry = self._geometry(x)
        return geometry, pair_angles(*geometry, self.I, self.J, return_index=True)[3]

    def view_pair_residuals(self, x, v, geometry):
        """``pair_residuals(x, by_view[v])`` when only view ``v``'s pose differs from the one ``geometry``
        (:meth:`_geometry` of other parameters) was computed at: only that view's rays are turned."""
        rays_w, C, cen_w = geometry
        R, t = self.model.poses(x)
        keep = rays_w[v].copy(), C[v].copy(), cen_w[v].copy()
        rays_w[v] = self.rays_cam[v] @ R[v]
        C[v] = -R[v].T @ t[v]
        cen_w[v] = self.centroid_cam[v] @ R[v]
        try:
            sel = self.by_view[v]
            psi, _, _ = pair_angles(rays_w, C, cen_w, self.I[sel], self.J[sel])
            return (psi[:, :2] - psi[:, 2:]) * self.scale[sel][:, None] * self.keep[sel]
        finally:
            rays_w[v], C[v], cen_w[v] = keep

    def residuals(self, x, weights=None):
        r = self.pair_residuals(x)
        if weights is not None:
            r = r * weights[:, None]
        return np.concatenate([r.ravel() / SIGMA_PX, self.model.prior(x)])

    def _pose_derivatives(self, x):
        """Each view's turn and centre move per unit of each parameter: ``(n, 3, K)`` rad and ``(n, 3, K)`` mm, world frame.

        Central differences of :meth:`Model.poses` (every parameter's two steps in one batch; the poses are
        smooth and cheap: relative errors near 1e-10); a view's turn ``theta`` moves its rays ``r`` (world
        frame) by ``theta x r``.
        """
        m = self.model
        K = m.n_params
        h = _steps(m)
        X = np.asarray(x, np.float64) + np.concatenate([np.diag(h), -np.diag(h)])
        R, t = m.poses(X)  # (2K, n, 3, 3), (2K, n, 3)
        R0, _ = m.poses(x)
        dR = (R[:K] - R[K:]) / (2 * h)[:, None, None, None]
        W = dR.swapaxes(-1, -2) @ R0  # d(R') R: antisymmetric, [theta]x
        turn = 0.5 * np.stack([W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]], axis=-1)
        C = -np.einsum("knba,knb->kna", R, t)
        move = (C[:K] - C[K:]) / (2 * h)[:, None, None]
        return turn.transpose(1, 2, 0), move.transpose(1, 2, 0)

    def jacobian(self, x, weights=None):
        """Jacobian of :meth:`residuals` by the chain rule.

        The tangent residuals: the extremal planes' derivatives (:func:`._tangents.pair_angle_derivatives`,
        at the extremal rays of ``x``) times the views' pose derivatives (:meth:`_pose_derivatives`); the prior
        by forward differences.  Until 2026-12-03 all of it was forward differences: one evaluation of every
        pair per shared parameter and of a view's pairs per angle, 70 % of a refinement's time.
        """
        m = self.model
        x = np.asarray(x, np.float64)
        (rays_w, C, cen_w), idx = self._extremal_rays(x)
        turn, move = pair_angle_derivatives(rays_w, C, cen_w, self.I, self.J, idx)
        D = np.concatenate(self._pose_derivatives(x), axis=1)  # (n, 6, K): each view's turn and move
        # view i's two angles minus view j's: each turns with its own view, all with the baseline C_j - C_i
        across = move[:, :2] - move[:, 2:]
        dpsi = (np.concatenate([turn[:, :2], -across], axis=2) @ D[self.I]
                + np.concatenate([-turn[:, 2:], across], axis=2) @ D[self.J])  # (P, 2, K)
        I = self.I
        P = len(I)
        wv = np.ones(P) if weights is None else weights
        p0 = m.prior(x)
        Jm = np.zeros((2 * P + len(p0), m.n_params))
        Jm[: 2 * P] = (dpsi * (self.scale[:, None] * self.keep * wv[:, None] / SIGMA_PX)[..., None]).reshape(2 * P, -1)
        h = _steps(m)
        for k in range(m.n_params):
            xk = x.copy()
            xk[k] += h[k]
            Jm[2 * P :, k] = (m.prior(xk) - p0) / h[k]
        return Jm

    def fit(self, x0, *, weights=None, max_iter=30, trend_first=False):
        """Robust Levenberg-Marquardt (soft-L1, :data:`F_SCALE`), deterministic; returns ``(x, info)``.

        ``trend_first``: the angles are first fitted with the stops' own errors held to
        :data:`SIGMA_JITTER_START_DEG`, then from there with the model's prior (the fit from the commanded angles).
        """
        m = self.model
        if trend_first and m.kind == "turntable" and m.angles_free and m.n >= 3:
            self.model = replace(m, jitter_deg=SIGMA_JITTER_START_DEG)
            try:
                x0, _ = robust_lm(lambda x: self.residuals(x, weights), lambda x: self.jacobian(x, weights), x0,
                                  max_iter=max_iter)
            finally:
                self.model = m
        return robust_lm(lambda x: self.residuals(x, weights), lambda x: self.jacobian(x, weights), x0, max_iter=max_iter)

    def view_rms(self, x, views=None, partners=None):
        """Per-view RMS (px) of the residuals of its pairs (with ``partners`` only, when given)."""
        r = self.pair_residuals(x)
        out = np.full(self.model.n, np.nan)
        for v in range(self.model.n) if views is None else views:
            sel = self.by_view[v]
            if partners is not None:
                other = np.where(self.I[sel] == v, self.J[sel], self.I[sel])
                sel = sel[np.isin(other, partners)]
            if len(sel):
                out[v] = float(np.sqrt(np.mean(r[sel] ** 2)))
        return out


def _steps(model):
    """The finite-difference step of each parameter, ``(n_params,)``: 1e-6 rad for the camera's rotation, 1e-4
    (degrees or mm) for the others."""
    h = np.full(model.n_params, 1e-4)
    h[: min(3, model.n_shared)] = 1e-6
    return h


def _soft_l1(r, f):
    z = (r / f) ** 2
    return 2 * f * f * (np.sqrt(1 + z) - 1), 1 / np.sqrt(1 + z)


def cost(r, f_scale=F_SCALE):
    """The soft-L1 cost ``sum rho(r)`` of residuals (units of their sigma)."""
    return float(_soft_l1(np.asarray(r, np.float64), f_scale)[0].sum())


def robust_lm(fun, jac, x0, *, f_scale=F_SCALE, max_iter=30, tol=1e-6):
    """Levenberg-Marquardt on a soft-L1 loss by iteratively reweighted normal equations.

    Small problems (tens of parameters): the normal equations are solved
    directly, no SVD of the Jacobian (``scipy.optimize.least_squares`` spends
    most of its time there here).  Returns ``(x, info)`` with ``cost``
    (``sum rho``), ``iterations``, ``converged``.
    """
    x = np.array(x0, dtype=np.float64)
    r = fun(x)
    rho, wt = _soft_l1(r, f_scale)
    cost = float(rho.sum())
    lam = 1e-3
    it = 0
    converged = False
    for it in range(1, max_iter + 1):
        J = jac(x)
        # einsum, not BLAS: on a loaded machine OpenBLAS's threads made these small products 3x slower
        A = np.einsum("pi,pj->ij", J, J * wt[:, None], optimize=False)
        g = np.einsum("pi,p->i", J, wt * r, optimize=False)
        D = np.diag(A).copy()
        D[D <= 0] = 1e-12
        improved = False
        for _ in range(12):
            try:
                dx = np.linalg.solve(A + lam * np.diag(D), -g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            xn = x + dx
            rn = fun(xn)
            rhon, wtn = _soft_l1(rn, f_scale)
            cn = float(rhon.sum())
            if cn < cost:
                small = cost - cn < tol * max(cost, 1e-12) or float(np.sqrt(np.sum(dx * dx * D))) < tol
                x, r, wt, cost = xn, rn, wtn, cn
                lam = max(lam / 3, 1e-9)
                improved = True
                break
            lam *= 4
        if not improved or small:
            converged = True
            break
    return x, {"cost": cost, "iterations": it, "converged": converged}
