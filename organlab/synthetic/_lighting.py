"""Scenes whose lighting or paint defeats a single-view silhouette (the joint silhouette step's test scenes).

Two looks the default renderer never makes, written over a complete session
of :func:`organlab.synthetic.make_session` (its calibration images stay, so
the session calibrates itself):

* ``"rim"``: a lamp at the camera (a head lamp) with little ambient light:
  the specimen's shade falls as ``|n . v|`` toward its outline, where it
  meets the dark backdrop and the plate at a few grey levels (strong rim
  shading);
* ``"dark_paint"``: a specimen painted with patches of dark paint
  (reflectance ``DARK_ALBEDO``, about 0.15) over its tissue texture, on a
  dark plate (:class:`Painted`); ``"even_paint"`` is the same specimen with
  patches of a mid-grey paint (an evenly textured comparison).

:func:`make_lit_session` renders the views and the background frames again
under the look, with the session's pixel noise.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera
from ..session import write_json
from . import _render
from ._session import _write_image, make_session
from ._specimens import Specimen, make_specimen

LOOKS = ("rim", "dark_paint", "even_paint")
#: Rim look: ambient and head-lamp shares of the specimen's shade.
RIM_AMBIENT = 0.25
RIM_DIFFUSE = 1.0
#: Paint: the dark patches' reflectance (of full scale), the even patches', and the dark plate's.
DARK_ALBEDO = 0.15
EVEN_ALBEDO = 0.45
DARK_PLATE = 0.16


class Painted(Specimen):
    """A specimen with patches of paint over its texture (``albedo`` 0-255 RGB).

    Parameters
    ----------
    specimen : Specimen
    reflectance : float
        The paint's reflectance (0-1 of full scale), neutral grey.
    seed : int
        Where the patches lie (a sum of random plane waves > ``level``).
    level : float
        Higher: fewer, smaller patches (a few mm to 15 mm across, some 10 % of the surface at 0.55).
    """

    def __init__(self, specimen, *, reflectance=DARK_ALBEDO, seed=0, level=0.55):
        self.inner = specimen
        self.volume = specimen.volume
        self.name = f"{specimen.name}-painted"
        self.bounds = specimen.bounds
        self.reflectance = float(reflectance)
        self.level = float(level)
        rng = np.random.default_rng([int(seed), 21])
        k = rng.normal(size=(6, 3))
        self._k = k / np.linalg.norm(k, axis=1, keepdims=True) * rng.uniform(0.25, 0.45, size=(6, 1))  # 14-25 mm waves
        self._phase = rng.uniform(0, 2 * np.pi, size=6)

    def _inside(self, p):
        return self.inner._inside(p)

    def _intersect(self, o, d, t_max=None):
        return self.inner._intersect(o, d, t_max)

    def _any_hit(self, o, d):
        return self.inner._any_hit(o, d)

    def patches(self, points):
        """(N,) bool: the points under paint."""
        p = np.asarray(points, np.float64)
        f = np.cos(p @ self._k.T + self._phase).mean(axis=1)
        return f > self.level / 2.0

    def albedo(self, points):
        a = np.array(self.inner.albedo(points), np.float64)
        m = self.patches(points)
        a[m] = 255.0 * self.reflectance * np.array([1.0, 0.97, 0.95])
        return a


def _cameras(truth):
    c = truth["camera"]
    K, dist, size = np.asarray(c["K"]), np.asarray(c["dist"]), tuple(c["image_size"])
    views = [Camera(K, dist, np.asarray(v["R"]), np.asarray(v["t"]), size) for v in truth["views"]]
    return views


def render_lit(camera, specimen, *, look, supersample=3):
    """Ray-cast the scene under a look (module docstring); float64 ``(H, W, 3)`` RGB.

    Parameters
    ----------
    camera : Camera
    specimen : Specimen or None
        None: the empty scene (a background frame).
    look : {'rim', 'dark_paint', 'even_paint'}
    supersample : int
    """
    if look not in LOOKS:
        raise ValueError(f"look must be one of {LOOKS}, got {look!r}")
    light = _render.LIGHT_CAM @ camera.R
    centre = camera.center
    d_cam_all = _render.camera_frame_rays(camera, supersample)
    n = d_cam_all.shape[0]
    out = np.empty((n, 3))
    for s in range(0, n, _render.CHUNK):
        d = _render.world_rays(camera, supersample, s, s + _render.CHUNK)
        o = np.broadcast_to(centre, d.shape)
        colour = _render.backdrop_layer(camera, supersample)[s : s + _render.CHUNK].astype(np.float64)
        t_best, albedo, normal = _render.plate_hits(o, d)
        m = np.isfinite(t_best)
        if look != "rim":
            albedo = albedo * (255.0 * DARK_PLATE / 128.0)
        colour[m] = _render.shade(albedo[m], normal[m], light)
        if specimen is not None:
            idx = _render.box_candidates(centre, d, *specimen.bounds)
            if idx.size:
                di = d[idx]
                t, nrm = specimen._intersect(np.broadcast_to(centre, di.shape), di, t_max=t_best[idx])
                hit = np.flatnonzero(t < t_best[idx])
                if hit.size:
                    p = centre + t[hit, None] * di[hit]
                    a = specimen.albedo(p)
                    if look == "rim":
                        ndv = np.abs(np.einsum("ij,ij->i", nrm[hit], di[hit]))
                        colour[idx[hit]] = a * (RIM_AMBIENT + RIM_DIFFUSE * ndv)[:, None]
                    else:
                        colour[idx[hit]] = _render.shade(a, nrm[hit], light)
        out[s : s + _render.CHUNK] = colour
    return _render.downsample(out, camera.image_size, supersample)


def make_lit_session(out_dir, *, look="rim", specimen="aaa-3", seed=3, noise_sigma=3.0, paint_seed=0, **kw):
    """A session (:func:`organlab.synthetic.make_session`, its calibration images kept) whose views and
    background frames are rendered under ``look``; returns its truth (``truth.json``, with ``look``).

    Parameters
    ----------
    out_dir : str or Path
    look : {'rim', 'dark_paint', 'even_paint'}
    specimen : str or Specimen
        Painted (:class:`Painted`) for the paint looks.
    seed : int
        Noise seed (as ``make_session``).
    noise_sigma : float
        Gaussian pixel noise, grey levels.
    paint_seed : int
        Where the paint patches lie.
    **kw
        More options of ``make_session`` (``n_views``, ``image_size``, ``supersample``, ...); not ``hard``.

    Examples
    --------
    >>> import tempfile
    >>> t = make_lit_session(tempfile.mkdtemp(), look="rim", n_views=4, image_size=(160, 120),
    ...                      views_only=True, n_background=2, supersample=1)
    >>> t["look"], len(t["views"])
    ('rim', 4)
    """
    if look not in LOOKS:
        raise ValueError(f"look must be one of {LOOKS}, got {look!r}")
    if kw.get("hard"):
        raise ValueError("make_lit_session: hard=True does not apply (the look is the lighting)")
    spec = make_specimen(specimen)
    if look != "rim" and not isinstance(spec, Painted):
        spec = Painted(spec, reflectance=DARK_ALBEDO if look == "dark_paint" else EVEN_ALBEDO, seed=paint_seed)
    out = Path(out_dir)
    truth = make_session(out, specimen=spec, seed=seed, noise_sigma=noise_sigma, **kw)
    ss = int(kw.get("supersample", 3))
    doc = truth["session_json"]
    cams = _cameras(truth)
    rng = np.random.default_rng

    def write(rel, img, kind, i):
        q = _render.quantize(img, noise_sigma, rng([int(seed), kind, i]))
        fmt = "jpg" if Path(rel).suffix.lower() in (".jpg", ".jpeg") else "png"
        _write_image(out / rel, q, fmt=fmt, quality=int(kw.get("jpeg_quality", 95)))

    empty = render_lit(cams[0], None, look=look, supersample=ss)
    for j, rel in enumerate(doc.get("background_images", [])):
        write(rel, empty, 3, j)
    for i, (v, cam) in enumerate(zip(doc["views"], cams)):
        write(v["image"], render_lit(cam, spec, look=look, supersample=ss), 4, i)
    truth["look"] = look
    write_json(out / "truth.json", truth)
    return truth
