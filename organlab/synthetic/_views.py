"""Rendering the specimen on the turntable: colour views and anti-aliased silhouettes."""

from __future__ import annotations

import numpy as np

from ..camera import Camera
from . import _render
from ._specimens import make_specimen


def render_view(specimen, camera, *, supersample=3, noise_sigma=0.0, seed=None, table=True):
    """Render the specimen on the turntable seen by ``camera``.

    Parameters
    ----------
    specimen : Specimen or str or None
        ``None`` renders the empty scene (a background frame).
    camera : Camera
        Pose world (table frame) to camera, e.g. ``default_camera().at_table_angle(a)``.
    supersample : int
        Sub-pixel samples per axis (box filter).
    noise_sigma : float
        Gaussian pixel noise, grey levels.
    seed : int or sequence of int, optional
        Seed of the noise.
    table : bool
        Show the turntable plate.

    Returns
    -------
    image : (H, W, 3) uint8
        RGB.
    """
    if int(supersample) < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    spec = None if specimen is None else make_specimen(specimen)
    img = _render.render(camera, supersample=int(supersample), specimen=spec, plate=table)
    return _render.quantize(img, noise_sigma, np.random.default_rng(seed))


def render_masks(specimen, cameras, *, supersample=4):
    """Anti-aliased silhouettes: the fraction of each pixel covered by the specimen.

    Parameters
    ----------
    specimen : Specimen or str
    cameras : Camera or sequence of Camera
    supersample : int
        Sub-pixel samples per axis; coverage is a multiple of ``1 / supersample**2``.

    Returns
    -------
    masks : (V, H, W) float32 in [0, 1]
        One per camera (``(H, W)`` for a single camera).
    """
    spec = make_specimen(specimen)
    single = isinstance(cameras, Camera)
    cams = [cameras] if single else list(cameras)
    if int(supersample) < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    out = np.stack([_render.coverage(c, spec, supersample=int(supersample)) for c in cams])
    return out[0] if single else out
