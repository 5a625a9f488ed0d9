"""Prepared views for silhouettes at any threshold (:class:`SilhouetteModel`).

Re-exported by :mod:`organlab.silhouette`: the background (a model of the
empty frames, or a backdrop colour), the noise floor and each view's
difference image are computed once; a new threshold then only thresholds,
cleans and computes the coverage (the viewer's and the threshold widget's
slider).  Both ways of finding a silhouette live behind it: background
subtraction (grey levels) and, for a session with a ``backdrop``, keying in
CIE Lab (Delta E, :mod:`organlab.silhouette._keying`).  The per-view steps run in a few
threads: cv2, numpy and the numba kernels release the GIL.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..errors import SessionError
from ..masks import Silhouette
from ..session import Session, load_session
from ._joint import MIN_VIEWS, joint_masks
from ._keying import KeyInfo, auto_key_threshold, clean_scaled, estimate_backdrop, key_distance
from ._subtract import RIM_DEPTH, _rim_mask, auto_threshold, background_model, background_noise, coverage, difference

__all__ = ["SilhouetteModel", "silhouettes", "session_silhouettes"]


class SilhouetteModel:
    """Views prepared for background subtraction, for silhouettes at any threshold.

    Holds what does not depend on the threshold: the background model, the
    noise floor of the automatic threshold, each view's difference image and
    (once asked for) its automatic threshold.  :meth:`silhouettes` then only
    thresholds, cleans and computes the sub-pixel coverage, so that the viewer
    and the threshold widget can re-run the stage on every slider move.
    ``SilhouetteModel.from_session(s).silhouettes(threshold=t)`` equals
    ``silhouettes(s, threshold=t)``, for sessions with background frames and
    for sessions with a ``backdrop`` alike.

    Parameters
    ----------
    images : sequence of (H, W) or (H, W, 3) uint8 or None
        One per view; None for a view whose silhouette is given in ``masks``.
    background_frames : sequence of (H, W) or (H, W, 3) uint8, optional
        Images of the empty scene; needed unless every view has a given mask.
    mode : {'color', 'grey'}
        As in :func:`difference`.
    background : {'median', 'mean'}
        As in :func:`background_model`.
    masks : sequence of (H, W) bool or None, optional
        Given silhouettes (used as they are), one per view or None.
    names : sequence of str, optional
        How errors name each view (default ``"view i"``).
    backdrop : dict, optional
        A session's ``backdrop`` (``{"color": "frames" | "border" | [r, g, b],
        "shadows": bool}``): the views are keyed in CIE Lab against it
        (:mod:`organlab.silhouette._keying`) instead of subtracted from the frames'
        model; ``"frames"`` needs ``background_frames``, ``"border"`` takes
        the median colour of the views' border bands.  ``mode`` does not
        apply then.
    rim_depth : int, px
        Subtraction at the automatic threshold: each view's silhouette keeps
        the dim rim connected to it, at most this many pixels out
        (:func:`organlab.silhouette.grow_rim`, hysteresis down to 3 times the
        background noise); 0 turns it off.  A threshold given
        (:meth:`silhouettes`'s ``threshold``, the slider, ``--threshold``) is
        used as it is, the user's outline, unless it is the view's automatic
        one (a face or a report giving it back).

    Attributes
    ----------
    background : (H, W) or (H, W, 3) float32, or (3,) float32 (a backdrop colour), or None
    keyed : bool
        Whether the views are keyed against a backdrop.
    units : str
        The threshold's units: ``'grey levels'`` (subtraction) or
        ``'Delta E'`` (CIE76 colour difference, keying).
    noise : float
        Subtraction: :func:`background_noise` of the frames, grey levels (0 for keying).
    floor : float
        Lowest automatic threshold (subtraction: 5 times
        :func:`background_noise`; keying: 0, its rule has its own noise term).
    differences : list of (H, W) float32 or None
        Per view, :func:`difference` of the image and the background, or
        the keyed views' Delta E (exposure divided out, cast shadows 0).
    gains : list of float
        Keyed views' exposure gains against the background (1 otherwise).
    """

    def __init__(self, images: Sequence[np.ndarray], background_frames: Sequence[np.ndarray] | None = None, *,
                 mode: Literal["color", "grey"] = "color", background: Literal["median", "mean"] = "median",
                 masks: Sequence[np.ndarray | None] | None = None, names: Sequence[str] | None = None,
                 backdrop: dict | None = None, rim_depth: int = RIM_DEPTH) -> None:
        images = list(images)
        n = len(images)
        masks = [None] * n if masks is None else list(masks)
        if len(masks) != n:
            raise ValueError(f"got {len(masks)} masks for {n} views")
        self.names = [f"view {i}" for i in range(n)] if names is None else list(names)
        self.mode = mode
        self.masks = [None if m is None else np.asarray(m) != 0 for m in masks]
        self.images = [None if m is not None else np.asarray(img) for img, m in zip(images, self.masks)]
        need = [i for i in range(n) if self.masks[i] is None]
        for i in need:
            if self.images[i] is None:
                raise ValueError(f"{self.names[i]}: no image and no given mask")
        self.backdrop = None if backdrop is None else dict(backdrop)
        self.keyed = self.backdrop is not None
        self.units = "Delta E" if self.keyed else "grey levels"
        self.background = None
        self.floor = 0.0
        self.noise = 0.0
        if isinstance(rim_depth, bool) or not isinstance(rim_depth, (int, np.integer)) or rim_depth < 0:
            raise ValueError(f"rim_depth must be an integer >= 0 (pixels; 0 turns the rim step off), got {rim_depth!r}")
        self.rim_depth = int(rim_depth)
        self.differences = [None] * n
        self.gains = [1.0] * n
        self._shadow = [0.0] * n
        self._auto = [None] * n
        self._auto_info = [None] * n
        self._rim = [None] * n  # per view, where its rim was kept (rim_near): the joint step's coverage uses it
        if need:
            self.background = self._background(background_frames, background, [self.images[i] for i in need])
            if not self.keyed:
                self.noise = background_noise(list(background_frames))
                self.floor = 5.0 * self.noise
            diffs = _map_views(lambda i: self._difference(i), need)
            for i, d in zip(need, diffs):
                self.differences[i] = d

    def _background(self, frames, method, images):
        """The background the views are compared with: the frames' model, or a backdrop colour."""
        color = self.backdrop.get("color", "frames") if self.keyed else "frames"
        if color == "border":
            return estimate_backdrop(images)
        if color != "frames":
            return np.asarray(color, np.float32)
        if frames is None:
            raise ValueError("background frames are needed for the views without a given mask")
        return background_model(list(frames), method=method)

    def _difference(self, i):
        try:
            if not self.keyed:
                return difference(self.images[i], self.background, mode=self.mode)

            d, self.gains[i], sh = key_distance(self.images[i], self.background,
                                                shadows=bool(self.backdrop.get("shadows", True)))
            self._shadow[i] = float(sh.mean())
            return d
        except ValueError as e:
            raise SessionError(f"{self.names[i]}: {e}") from None

    @classmethod
    def from_session(cls, session: Session | str | Path, *, images: Sequence[np.ndarray] | None = None,
                     views: Sequence[int] | None = None, mode: Literal["color", "grey"] = "color",
                     background: Literal["median", "mean"] = "median") -> SilhouetteModel:
        """Prepare a session's views (as :func:`organlab.silhouette.silhouettes` reads them).

        Parameters
        ----------
        session : Session
        images : sequence of (H, W) or (H, W, 3) uint8, optional
            The images of ``views``, already read (one per view taken);
            read from the session when omitted.
        views : sequence of int, optional
            Only these views (default every one), in this order.  A
            ``"border"`` backdrop is still estimated over every view without
            a mask, so that these views are keyed as the whole session is.
        mode : {'color', 'grey'}
        background : {'median', 'mean'}

        Returns
        -------
        SilhouetteModel
        """
        idx = list(range(len(session.views))) if views is None else [int(i) for i in views]
        if images is not None and len(images) != len(idx):
            raise ValueError(f"got {len(images)} images for {len(idx)} views")
        given = dict(zip(idx, images)) if images is not None else {}

        def image(i):
            return given[i] if i in given else session.read(session.views[i].image, key=f"views[{i}].image")

        masks, imgs, names = [], [], []
        for i in idx:
            view = session.views[i]
            names.append(f"{session.json_path}: views[{i}] ({session.relpath(view.image)})")
            if view.mask is not None:
                masks.append(session.read(view.mask, key=f"views[{i}].mask", grey=True) > 0)
                imgs.append(None)
            else:
                masks.append(None)
                imgs.append(image(i))
        frames = None
        backdrop = getattr(session, "backdrop", None)
        needs_frames = backdrop is None or backdrop.get("color") == "frames"
        if any(m is None for m in masks) and needs_frames:
            frames = [session.read(p, key=f"background_images[{j}]") for j, p in enumerate(session.background_images)]
        if backdrop is not None and backdrop.get("color") == "border" and len(idx) < len(session.views):
            every = [image(i) for i, v in enumerate(session.views) if v.mask is None]
            backdrop = {**backdrop, "color": tuple(float(c) for c in estimate_backdrop(every))}
        return cls(imgs, frames, mode=mode, background=background, masks=masks, names=names, backdrop=backdrop)

    def __len__(self):
        return len(self.images)

    def auto_thresholds(self) -> list[float | None]:
        """Each view's automatic threshold, None for given masks; cached.

        Subtraction: Li's, at least :attr:`floor`.  Keying: from the border
        band's noise and clutter and the background next to the specimen,
        capped by Li's (:func:`organlab.silhouette._keying.auto_key_threshold`).
        """
        todo = [i for i in range(len(self)) if self.masks[i] is None and self._auto[i] is None]
        for i, t in zip(todo, _map_views(self._auto_threshold, todo)):
            self._auto[i] = t
        return list(self._auto)

    def auto_threshold(self, i: int) -> float | None:
        """View ``i``'s automatic threshold (as :meth:`auto_thresholds`, one view; None for a given mask)."""
        if not 0 <= i < len(self):
            raise IndexError(f"view {i} out of range: {len(self)} views")
        if self.masks[i] is None and self._auto[i] is None:
            self._auto[i] = self._auto_threshold(i)
        return self._auto[i]

    def _auto_threshold(self, i):
        if self.keyed:
            t, *reasons = auto_key_threshold(self.differences[i])
            self._auto_info[i] = (float(t), *reasons)
            return float(t)
        try:
            return auto_threshold(self.differences[i], floor=self.floor)
        except ValueError as e:
            raise SessionError(f"{self.names[i]}: {e}") from None

    def silhouettes(self, *, threshold: float | None = None, progress: Callable[[int, int], object] | None = None,
                    **clean: Any) -> list[Silhouette]:
        """Silhouettes of every view at a threshold.

        Parameters
        ----------
        threshold : float, optional
            In :attr:`units`, the same for every view; the automatic
            threshold per view when omitted.
        progress : callable(done, total), optional
        **clean
            Options of :func:`clean_mask` (subtraction; keying cleans with
            radii from the image scale, :func:`organlab.silhouette._keying.clean_scaled`).

        Returns
        -------
        list of Silhouette, one per view

        Raises
        ------
        SessionError
            A threshold <= 0, or a view whose silhouette is empty.
        """
        if threshold is None:
            thresholds = self.auto_thresholds()
        else:
            thresholds = [self._checked(threshold)] * len(self)
        n = len(self)
        out = []
        auto = threshold is None  # the dim rim is kept at the automatic thresholds (grow_rim)
        for i, sil in enumerate(_map_views(lambda i: self._silhouette(i, thresholds[i], clean, auto), range(n))):
            out.append(sil)
            if progress is not None:
                progress(i + 1, n)
        return out

    def silhouette(self, i: int, *, threshold: float | None = None, **clean: Any) -> Silhouette:
        """The silhouette of view ``i`` at a threshold (in :attr:`units`; its automatic one when omitted).

        Returns
        -------
        Silhouette
        """
        if not 0 <= i < len(self):
            raise IndexError(f"view {i} out of range: {len(self)} views")
        if threshold is None:
            t = self.auto_thresholds()[i] if self.masks[i] is None else None
        else:
            t = self._checked(threshold)
        return self._silhouette(i, t, clean, threshold is None)

    def _checked(self, threshold):
        t = float(threshold)
        if not t > 0:
            raise SessionError(f"threshold must be > 0 {self.units}, got {t}")
        return t

    def _silhouette(self, i, t, clean, auto=False):
        if self.masks[i] is not None:
            m = self.masks[i]
            return Silhouette(m, m.astype(np.float32), None, "given")
        if self.keyed:
            return self._keyed(i, t, clean)
        auto = auto or (self._auto[i] is not None and t == self._auto[i])  # the automatic one, given back
        mask, near = _rim_mask(self.differences[i], self.images[i], self.background, t, clean, noise=self.noise,
                               depth=self.rim_depth if auto else 0)
        if not mask.any():
            raise SessionError(
                f"{self.names[i]}: the silhouette is empty; lower --threshold or check the background frames"
            )
        self._rim[i] = near
        cov = coverage(self.images[i], self.background, mask, near=self._rim[i])
        return Silhouette(mask, cov, t, "subtraction")

    def _keyed(self, i, t, clean):
        if clean:
            raise ValueError(f"clean-up options {sorted(clean)} do not apply to keyed views (a backdrop session): "
                             "keying scales its clean-up to the image")
        mask, r = clean_scaled(self.differences[i] > t)
        if not mask.any():
            raise SessionError(f"{self.names[i]}: the keyed silhouette is empty; check backdrop.color or lower --threshold")
        auto = self._auto_info[i]
        if auto is not None and auto[0] == t:
            reason, noise, clutter, li, ring = auto[1:]
        else:
            reason, noise, clutter, li, ring = "given", None, None, None, None
        info = KeyInfo(float(t), reason, noise, clutter, li, self.gains[i], self._shadow[i], r, ring)
        bg = self.background
        full = np.broadcast_to(bg, np.shape(self.images[i])) if np.ndim(bg) == 1 else bg
        cov = coverage(self.images[i], np.asarray(full, np.float32) * self.gains[i], mask)
        return Silhouette(mask, cov, float(t), "backdrop", info.to_dict())


    def joint(self, silhouettes: Sequence[Silhouette], cameras: Sequence[Any], box: tuple, *,
              iterations: int | None = None) -> tuple[list[Silhouette], dict]:
        """The silhouettes segmented again with the model of all the views as a prior (the joint step).

        Each view's first-pass silhouette is refined against the projection
        of the tolerant visual hull of every view and its own difference
        image (:mod:`organlab.silhouette._joint`): pixels the other views
        require and whose colour differs from the background are added,
        pixels that no view's hull explains are dropped; iterated to
        agreement.  Given masks are kept as they are.  Keyed views (a
        backdrop session) get the required rule (what only this view carves
        and other views need) and the removal, not the edge and region
        rules: against one backdrop colour a dark specimen's shadowed parts,
        the dark stand and the shadows beside it have the same Delta E (the
        dinoSparseRing photos: 2-10 for all three), so a whole region has no
        colour evidence (the region rule lowered the like-with-like IoU
        0.980 -> 0.972 there) and the edge rule followed the stand through a
        gap (1 491 px in dinoSR0001).

        Parameters
        ----------
        silhouettes : sequence of Silhouette
            The first pass (:meth:`silhouettes`), one per view.
        cameras : sequence of Camera
            One per view.
        box : ((3,), (3,)) float, mm
            Where the specimen lies (the session's roi); the prior is carved
            in it.
        iterations : int, optional
            At most this many rounds (default ``organlab.silhouette._joint.ITERATIONS``).

        Returns
        -------
        silhouettes : list of Silhouette
            Changed views have a new mask and coverage; each view's ``info``
            gains ``joint``: ``{"added": px, "removed": px}``.
        summary : dict
            ``iterations``, ``seconds``, ``voxel_mm``, ``views`` (per view
            ``added``, ``removed``).
        """
        sils = list(silhouettes)
        if len(sils) != len(self) or len(cameras) != len(self):
            raise ValueError(f"joint: got {len(sils)} silhouettes and {len(cameras)} cameras for {len(self)} views")
        kw = {} if iterations is None else {"iterations": int(iterations)}
        masks, summary = joint_masks([s.mask for s in sils], self.differences, list(cameras), box,
                                     keyed=self.keyed, **kw)
        out = []
        for i, (s, m, row) in enumerate(zip(sils, masks, summary["views"])):
            change = {"added": row["added"], "removed": row["removed"]}
            info = {**(s.info or {}), "joint": change}
            if (row["added"] or row["removed"]) and self.masks[i] is None and m.any():
                out.append(Silhouette(m, self._coverage(i, m), s.threshold, s.source, info))
            else:
                out.append(Silhouette(s.mask, s.coverage, s.threshold, s.source, info))
        return out, summary

    def joint_applies(self) -> bool:
        """Whether ``joint_silhouettes="auto"`` (the default) runs the joint step: a keyed session (a backdrop) of
        at least MIN_VIEWS views, one not given.  Background subtraction keeps its per-view silhouettes unless the
        step is asked for (``"on"``): on the sample it changes 4 px and costs about a third of the command."""
        return self.keyed and len(self) >= MIN_VIEWS and any(d is not None for d in self.differences)

    def _coverage(self, i, mask):
        if not self.keyed:
            return coverage(self.images[i], self.background, mask, near=self._rim[i])
        bg = self.background
        full = np.broadcast_to(bg, np.shape(self.images[i])) if np.ndim(bg) == 1 else bg
        return coverage(self.images[i], np.asarray(full, np.float32) * self.gains[i], mask)


def _map_views(fn, indices):
    """``[fn(i) for i in indices]`` in a few threads (the cv2, numpy and numba steps release the GIL)."""
    indices = list(indices)
    workers = max(1, min(len(indices), os.cpu_count() or 1))
    if workers == 1:
        return [fn(i) for i in indices]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(fn, indices))


def silhouettes(
    session: Session | str | Path,
    *,
    images: Sequence[np.ndarray] | None = None,
    threshold: float | None = None,
    mode: Literal["color", "grey"] = "color",
    background: Literal["median", "mean"] = "median",
    progress: Callable[[int, int], object] | None = None,
    **clean: Any,
) -> list[Silhouette]:
    """Silhouettes of every view of a session.

    A view with a ``mask`` in ``session.json`` uses it as given (non-zero =
    specimen); the others are found by background subtraction against the
    model of ``background_images`` or, when the session declares a
    ``backdrop``, by keying against it in CIE Lab (:mod:`organlab.silhouette._keying`).
    Through :class:`SilhouetteModel`, as the viewer and the widgets.

    Parameters
    ----------
    session : Session or str or Path
    images : sequence of (H, W) or (H, W, 3) uint8, optional
        The views' images, already read (one per view); read from the session
        when omitted.
    threshold : float, optional
        The same for every view, grey levels (subtraction) or Delta E
        (keying); automatic per view when omitted.
    mode : {'color', 'grey'}
    background : {'median', 'mean'}
    progress : callable(done, total), optional

    Returns
    -------
    list of Silhouette, one per view

    Examples
    --------
    >>> import tempfile
    >>> import organlab as ol
    >>> from organlab.synthetic import with_true_cameras
    >>> s = ol.load_session(with_true_cameras("sample_sessions/aaa_phantom", tempfile.mkdtemp() + "/aaa", step=6))
    >>> sils = ol.silhouettes(s)  # background subtraction, Li's threshold per view
    >>> len(sils), sils[0].mask.shape, sils[0].source, round(sils[0].threshold, 1)
    (6, (480, 640), 'subtraction', 17.5)
    >>> [int(sil.mask.sum()) for sil in sils]  # specimen pixels per view
    [11333, 10954, 11179, 11363, 11037, 11218]
    """
    if not isinstance(session, Session):
        session = load_session(session)
    model = SilhouetteModel.from_session(session, images=images, mode=mode, background=background)
    return model.silhouettes(threshold=threshold, progress=progress, **clean)


#: The name this function had before organlab 0.2; same function.
session_silhouettes = silhouettes
