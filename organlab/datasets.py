"""Public multi-view data sets, loaded into organlab's conventions.

* :func:`load_middlebury` -- a Middlebury multi-view stereo set (Seitz et
  al., CVPR 2006; e.g. ``dinoSparseRing``): images, cameras in mm, the
  object's bounding box;
* :func:`middlebury_silhouettes` -- silhouettes by the authors' recipe for
  their dark-background sets (threshold, dilate, erode);
* :func:`write_middlebury_session` -- a set's well-segmented views written
  as an organlab session keyed against its black backdrop (published
  cameras, no masks, no background frames).

The silhouette of a reconstruction seen by one of the set's cameras, to
compare with the photographs, is :func:`organlab.raster.model_mask`.

A Middlebury folder holds ``<name>_par.txt`` (first line: the number of
images; then one line per image ``name.png k11 .. k33 r11 .. r33 t1 t2 t3``,
row-major, with ``x = K [R | t] X`` and ``X`` in metres), the images, and
optionally ``README.txt`` (its "bounding box" lines, metres) and
``<name>_good_silhouette_images.txt`` (images whose silhouettes are usable).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .camera import Camera
from .errors import OrganlabError
from .session import write_json

__all__ = ["DatasetError", "MiddleburyData", "load_middlebury", "middlebury_silhouettes", "write_middlebury_session"]


class DatasetError(OrganlabError, ValueError):
    """A data set folder is missing files or holds malformed ones."""


class MiddleburyData(NamedTuple):
    """A loaded Middlebury set.

    Attributes
    ----------
    images : list of (H, W, 3) uint8 RGB
    cameras : list of Camera
        World to camera, mm (the set's metres x 1000), no distortion.
    bbox : (2, 3) float64, mm, world frame, or None
        ``[min, max]`` corners of the object's bounding box (from README.txt).
    names : list of str
        Image file names, in the order of ``images``.
    good : (N,) bool
        Images listed in ``*_good_silhouette_images.txt`` (all True when
        the file is absent).
    """

    images: list
    cameras: list
    bbox: np.ndarray | None
    names: list
    good: np.ndarray


def _read_bbox(readme):
    """The two ``(x y z)`` triples after "bounding box" in README.txt, metres."""
    text = readme.read_text(errors="replace")
    at = text.lower().find("bounding box")
    if at < 0:
        return None
    num = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
    triples = re.findall(rf"\(\s*({num})[\s,]+({num})[\s,]+({num})\s*\)", text[at:])
    if len(triples) < 2:
        raise DatasetError(f"{readme}: 'bounding box' is not followed by two (x y z) triples; fix or remove the file")
    return np.array(triples[:2], dtype=np.float64)


def load_middlebury(folder):
    """Load a Middlebury multi-view set: images, cameras in mm, bounding box.

    Parameters
    ----------
    folder : str or Path
        The set's folder, holding exactly one ``*_par.txt``.

    Returns
    -------
    MiddleburyData
        ``(images, cameras, bbox, names, good)``; cameras have
        ``K`` as given, ``dist = 0``, ``R`` as given (snapped to the nearest
        rotation when it is orthonormal only to the printed digits), ``t`` in
        mm (x 1000) and ``image_size`` of their image; ``bbox`` in mm.

    Raises
    ------
    DatasetError
        Missing folder, parameter file or image; malformed lines.
    """
    import cv2

    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: no such folder; give the folder of a Middlebury set (e.g. dinoSparseRing)")
    pars = sorted(folder.glob("*_par.txt"))
    if len(pars) != 1:
        raise DatasetError(f"{folder}: expected exactly one *_par.txt camera file, found {len(pars)}")
    par = pars[0]
    lines = [ln.split() for ln in par.read_text().splitlines() if ln.strip()]
    try:
        n = int(lines[0][0])
    except (IndexError, ValueError):
        raise DatasetError(f"{par}: the first line must be the number of images") from None
    if len(lines) - 1 != n:
        raise DatasetError(f"{par}: announces {n} images but has {len(lines) - 1} camera lines")
    images, cameras, names = [], [], []
    for i, fields in enumerate(lines[1:], start=2):
        if len(fields) != 22:
            raise DatasetError(f"{par}, line {i}: expected 'name.png' and 21 numbers (K, R, t), got {len(fields)} fields")
        name = fields[0]
        try:
            values = np.array(fields[1:], dtype=np.float64)
        except ValueError:
            raise DatasetError(f"{par}, line {i}: non-numeric camera parameters") from None
        path = folder / name
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise DatasetError(f"{path}: missing or unreadable image listed in {par.name}")
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        K, R, t = values[:9].reshape(3, 3), values[9:18].reshape(3, 3), values[18:] * 1000.0
        # the files' rotations are orthonormal to ~1.5e-6 only (printed digits): snap to
        # the nearest rotation (moves projections by < 0.01 px)
        U, _, Vt = np.linalg.svd(R)
        if np.abs(R - U @ Vt).max() < 1e-4 and np.linalg.det(U @ Vt) > 0:
            R = U @ Vt
        try:
            cam = Camera(K, np.zeros(5), R, t, (image.shape[1], image.shape[0]))
        except ValueError as e:
            raise DatasetError(f"{par}, line {i}: {e}") from None
        images.append(image)
        cameras.append(cam)
        names.append(name)
    readme = folder / "README.txt"
    bbox = _read_bbox(readme) * 1000.0 if readme.is_file() else None
    if bbox is not None:
        bbox = np.sort(bbox, axis=0)
    good = np.ones(n, dtype=bool)
    good_files = sorted(folder.glob("*_good_silhouette_images.txt"))
    if good_files:
        listed = set(good_files[0].read_text().split())
        good = np.array([nm in listed for nm in names])
    return MiddleburyData(images, cameras, bbox, names, good)


def _disk(radius):
    import cv2

    r = int(radius)
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def middlebury_silhouettes(images, *, threshold=0.19, dilate_px=10, erode_px=7, soft_width=None):
    """Silhouettes of an object on a black background, by the set authors' recipe.

    The recipe of the Middlebury README: threshold the grey level at 0.19
    (grey in ``[0, 1]``), dilate by 10 px, erode by 7 px (disk-shaped
    structuring elements; a net growth of 3 px that closes dark shadows on
    the object -- conservative for a visual hull).

    Parameters
    ----------
    images : sequence of (H, W, 3) uint8 RGB or (H, W) uint8 grey
    threshold : float
        Grey level in ``[0, 1]`` (grey = 0.299 R + 0.587 G + 0.114 B).
    dilate_px, erode_px : int
        Radii of the disks, px (0 skips the step).
    soft_width : float, optional
        When given, return float coverage images instead of bool masks: the
        same dilation and erosion applied to the grey image itself (grey
        morphology commutes with thresholding), mapped to
        ``clip(0.5 + (grey - threshold) / soft_width, 0, 1)``.  Their 0.5
        level is the recipe's outline, located between pixel centres
        (for :func:`organlab.carving.hull_field`).

    Returns
    -------
    list of (H, W) bool (or float32 in ``[0, 1]`` with ``soft_width``)
        ``masks[i] > 0.5`` equals the bool recipe.
    """
    import cv2

    if not 0.0 < threshold < 1.0:
        raise ValueError(f"threshold must be a grey level in (0, 1), got {threshold}")
    if soft_width is not None and not soft_width > 0:
        raise ValueError(f"soft_width must be > 0 (grey levels in [0, 1]), got {soft_width}")
    if min(dilate_px, erode_px) < 0:
        raise ValueError("dilate_px and erode_px must be >= 0")
    out = []
    for i, im in enumerate(images):
        a = np.asarray(im)
        if a.dtype != np.uint8 or a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3):
            raise ValueError(f"image {i} must be (H, W, 3) RGB or (H, W) grey uint8, got {a.shape} {a.dtype}")
        grey = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY) if a.ndim == 3 else a
        g = grey.astype(np.float32) / 255.0
        if soft_width is None:
            g = (g > threshold).astype(np.uint8)
        if dilate_px:
            g = cv2.dilate(g, _disk(dilate_px))
        if erode_px:
            g = cv2.erode(g, _disk(erode_px))
        if soft_width is None:
            out.append(g.astype(bool))
        else:
            out.append(np.clip(0.5 + (g - threshold) / soft_width, 0.0, 1.0).astype(np.float32))
    return out


def write_middlebury_session(data, source, folder, *, margin_mm=4.0):
    """Write a Middlebury set's good views as an organlab backdrop session (keyed against the border's colour).

    The views listed as good (``data.good``) are copied into ``folder/views``
    and ``folder/session.json`` gets their published cameras (``pose`` per
    view, one ``camera.K``: the set's views share it), the set's bounding box
    grown by ``margin_mm`` as the roi, and ``"backdrop": {"color": "border"}``:
    organlab finds the silhouettes itself, by keying against the image
    border's colour (no masks, no background frames).

    Parameters
    ----------
    data : MiddleburyData
        The set, from :func:`load_middlebury` (with a bounding box).
    source : str or Path
        Its folder (the images are copied from there).
    folder : str or Path
        Where the session goes (created; it must not hold a ``views`` folder yet).
    margin_mm : float, keyword-only
        The roi's margin around the bounding box, mm.

    Returns
    -------
    list of int
        The indices (into ``data``) of the views written, in order.

    Examples
    --------
    >>> import tempfile
    >>> from organlab.camera import Camera
    >>> import cv2
    >>> src = Path(tempfile.mkdtemp())
    >>> cv2.imwrite(str(src / "a.png"), np.zeros((4, 6, 3), np.uint8))
    True
    >>> cam = Camera(np.diag([5.0, 5.0, 1.0]), np.zeros(5), np.eye(3), [0.0, 0.0, 100.0], (6, 4))
    >>> data = MiddleburyData([np.zeros((4, 6, 3), np.uint8)], [cam], np.array([[-1.0, -1, -1], [1, 1, 1]]),
    ...                       ["a.png"], np.array([True]))
    >>> write_middlebury_session(data, src, src / "session")
    [0]
    >>> sorted(p.name for p in (src / "session").iterdir())
    ['session.json', 'views']
    """
    import shutil

    if data.bbox is None:
        raise DatasetError("write_middlebury_session: the set has no bounding box (README.txt); the roi needs one")
    source, folder = Path(source), Path(folder)
    good = [int(i) for i in np.flatnonzero(data.good)]
    if not good:
        raise DatasetError(f"{source}: no view is listed as having a good silhouette")
    K = data.cameras[good[0]].K
    if any(not np.allclose(data.cameras[i].K, K, rtol=1e-6, atol=1e-9) for i in good):
        raise DatasetError(f"{source}: the views' K differ; a session has one camera (calibrate it per view instead)")
    (folder / "views").mkdir(parents=True)
    for i in good:
        shutil.copy(source / data.names[i], folder / "views" / data.names[i])
    h, w = data.images[good[0]].shape[:2]
    write_json(folder / "session.json", {
        "format": "organlab.session/1", "units": "mm", "image_size": [w, h],
        "camera": {"K": K.tolist(), "dist": [0, 0, 0, 0, 0]},
        "views": [{"image": f"views/{data.names[i]}", "angle_deg": 0.0,
                   "pose": {"R": data.cameras[i].R.tolist(), "t": data.cameras[i].t.tolist()}} for i in good],
        "roi": {"min": (data.bbox[0] - margin_mm).tolist(), "max": (data.bbox[1] + margin_mm).tolist()},
        "backdrop": {"color": "border"},
    })
    return good
