"""The hard lighting of synthetic sessions (``make_session(..., hard=True)``).

Unlike the default renderer's soft, mostly ambient light, a lamp fixed to
the camera rig (upper left, in front of the specimen) lights the scene
directionally: Lambertian shading with little ambient light, cast shadows
(of the specimen on the plate and on itself), and Blinn-Phong specular
highlights on the specimen.  Each view's exposure differs (a gain drawn
within about +-10 %), and the images are noisy and JPEG-compressed (4:2:0
chroma, as most cameras write) by the session writer.  Background frames
are the same scene without the specimen (no shadow), at gain 1.
"""

from __future__ import annotations

import numpy as np

from . import _render

AMBIENT = 0.30
DIFFUSE = 0.80
SPECULAR = 0.45  # of full scale, white
SHININESS = 30.0
# Unit vector toward the lamp, camera frame: above, left, somewhat toward the camera.
LIGHT_CAM = np.array([-0.55, -0.75, -0.40]) / np.linalg.norm([-0.55, -0.75, -0.40])
#: Largest relative exposure change between views.
EXPOSURE_SPREAD = 0.10


def exposure_gain(rng):
    """A view's exposure gain, uniform in ``1 +- EXPOSURE_SPREAD``."""
    return 1.0 + rng.uniform(-EXPOSURE_SPREAD, EXPOSURE_SPREAD)


def _lit(albedo, normals, light, view_dir, shadow, *, specular):
    """Lambert + ambient (+ Blinn-Phong) shading, ``(N, 3)``; shadowed points get ambient only."""
    ndl = np.einsum("ij,j->i", normals, light)
    lam = np.where(shadow, 0.0, np.clip(ndl, 0.0, None))
    col = albedo * (AMBIENT + DIFFUSE * lam)[:, None]
    if specular:
        h = light[None, :] - view_dir
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        s = np.clip(np.einsum("ij,ij->i", normals, h), 0.0, None) ** SHININESS
        s = np.where(shadow | (ndl <= 0), 0.0, s)
        col = col + (255.0 * SPECULAR * s)[:, None]
    return col


def _in_shadow(points, normals, light, specimen):
    """Points whose ray toward the lamp hits the specimen."""
    if specimen is None or len(points) == 0:
        return np.zeros(len(points), bool)
    o = points + 0.05 * normals + 0.05 * light
    d = np.broadcast_to(light, o.shape).copy()
    out = np.zeros(len(points), bool)
    idx = _render.box_candidates_each(o, d, *specimen.bounds)  # the rays that can hit it (as render's)
    if idx.size:
        out[idx] = specimen._any_hit(o[idx], d[idx])
    return out


def render_hard(camera, *, supersample, specimen=None, plate=True):
    """Ray-cast the scene under the hard lamp; float64 ``(H, W, 3)`` RGB (may exceed 255 in highlights).

    Parameters
    ----------
    camera : Camera
        Pose world (table frame) to camera.
    supersample : int
        Sub-pixel samples per axis (box filter).
    specimen : Specimen, optional
        ``None`` renders the empty scene.
    plate : bool
        Show the turntable plate.

    Returns
    -------
    (H, W, 3) float64
    """
    light = LIGHT_CAM @ camera.R  # R.T @ l_cam: world frame
    centre = camera.center
    d_cam_all = _render.camera_frame_rays(camera, supersample)
    n = d_cam_all.shape[0]
    out = np.empty((n, 3))
    for s in range(0, n, _render.CHUNK):
        d = _render.world_rays(camera, supersample, s, s + _render.CHUNK)
        o = np.broadcast_to(centre, d.shape)
        colour = _render.backdrop_layer(camera, supersample)[s : s + _render.CHUNK].astype(np.float64)
        t_best = np.full(len(d), np.inf)
        if plate:
            t, albedo, normal = _render.plate_hits(o, d)
            m = np.flatnonzero(np.isfinite(t))
            p = centre + t[m, None] * d[m]
            colour[m] = _lit(albedo[m], normal[m], light, d[m], _in_shadow(p, normal[m], light, specimen), specular=False)
            t_best = t
        if specimen is not None:
            idx = _render.box_candidates(centre, d, *specimen.bounds)
            if idx.size:
                di = d[idx]
                t, normal = specimen._intersect(np.broadcast_to(centre, di.shape), di, t_max=t_best[idx])
                hit = np.flatnonzero(t < t_best[idx])
                if hit.size:
                    p = centre + t[hit, None] * di[hit]
                    nrm = normal[hit]
                    shadow = _in_shadow(p, nrm, light, specimen)
                    colour[idx[hit]] = _lit(specimen.albedo(p), nrm, light, di[hit], shadow, specular=True)
        out[s : s + _render.CHUNK] = colour
    return _render.downsample(out, camera.image_size, supersample)
