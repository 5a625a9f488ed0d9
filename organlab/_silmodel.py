"""Prepared views for silhouettes at any threshold (:class:`SilhouetteModel`).

Re-exported by :mod:`organlab.silhouette`: the background model, the noise
floor and each view's difference image are computed once; a new threshold
then only thresholds, cleans and computes the coverage (the viewer's and the
threshold widget's slider).  The per-view steps run in a few threads: cv2,
numpy and the numba kernels release the GIL.
"""

from __future__ import annotations

import numpy as np

from .errors import SessionError
from .silhouette import Silhouette, auto_threshold, background_model, background_noise, clean_mask, coverage, difference

__all__ = ["SilhouetteModel"]


class SilhouetteModel:
    """Views prepared for background subtraction, for silhouettes at any threshold.

    Holds what does not depend on the threshold: the background model, the
    noise floor of the automatic threshold, each view's difference image and
    (once asked for) its automatic threshold.  :meth:`silhouettes` then only
    thresholds, cleans and computes the sub-pixel coverage, so that the viewer
    and the threshold widget can re-run the stage on every slider move.
    ``SilhouetteModel.from_session(s).silhouettes(threshold=t)`` equals
    ``silhouettes(s, threshold=t)``.

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

    Attributes
    ----------
    background : (H, W) or (H, W, 3) float32 or None
    floor : float, grey levels
        Lowest automatic threshold: 5 times :func:`background_noise`.
    differences : list of (H, W) float32 or None
        Per view, :func:`difference` of the image and the background.
    """

    def __init__(self, images, background_frames=None, *, mode="color", background="median", masks=None, names=None):
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
        self.background = None
        self.floor = 0.0
        self.differences = [None] * n
        self._auto = [None] * n
        if need:
            if background_frames is None:
                raise ValueError("background frames are needed for the views without a given mask")
            frames = list(background_frames)
            self.background = background_model(frames, method=background)
            self.floor = 5.0 * background_noise(frames)
            diffs = _map_views(lambda i: self._difference(i), need)
            for i, d in zip(need, diffs):
                self.differences[i] = d

    def _difference(self, i):
        try:
            return difference(self.images[i], self.background, mode=self.mode)
        except ValueError as e:
            raise SessionError(f"{self.names[i]}: {e}") from None

    @classmethod
    def from_session(cls, session, *, images=None, mode="color", background="median"):
        """Prepare every view of a session (as :func:`organlab.silhouette.silhouettes` reads it).

        Parameters
        ----------
        session : Session
        images : sequence of (H, W) or (H, W, 3) uint8, optional
            The views' images, already read; read from the session when omitted.
        mode : {'color', 'grey'}
        background : {'median', 'mean'}

        Returns
        -------
        SilhouetteModel
        """
        n = len(session.views)
        if images is not None and len(images) != n:
            raise ValueError(f"got {len(images)} images for {n} views")
        masks, imgs, names = [], [], []
        for i, view in enumerate(session.views):
            names.append(f"{session.json_path}: views[{i}] ({session.relpath(view.image)})")
            if view.mask is not None:
                masks.append(session.read(view.mask, key=f"views[{i}].mask", grey=True) > 0)
                imgs.append(None)
            else:
                masks.append(None)
                imgs.append(images[i] if images is not None else session.read(view.image, key=f"views[{i}].image"))
        frames = None
        if any(m is None for m in masks):
            frames = [session.read(p, key=f"background_images[{j}]") for j, p in enumerate(session.background_images)]
        return cls(imgs, frames, mode=mode, background=background, masks=masks, names=names)

    def __len__(self):
        return len(self.images)

    def auto_thresholds(self):
        """Each view's automatic threshold (Li's, at least :attr:`floor`), None for given masks; cached."""
        todo = [i for i in range(len(self)) if self.masks[i] is None and self._auto[i] is None]
        for i, t in zip(todo, _map_views(self._auto_threshold, todo)):
            self._auto[i] = t
        return list(self._auto)

    def _auto_threshold(self, i):
        try:
            return auto_threshold(self.differences[i], floor=self.floor)
        except ValueError as e:
            raise SessionError(f"{self.names[i]}: {e}") from None

    def silhouettes(self, *, threshold=None, progress=None, **clean):
        """Silhouettes of every view at a threshold.

        Parameters
        ----------
        threshold : float, optional
            Grey levels, the same for every view; the automatic threshold per
            view when omitted.
        progress : callable(done, total), optional
        **clean
            Options of :func:`clean_mask`.

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
            if not float(threshold) > 0:
                raise SessionError(f"threshold must be > 0 grey levels, got {float(threshold)}")
            thresholds = [float(threshold)] * len(self)
        n = len(self)
        out = []
        for i, sil in enumerate(_map_views(lambda i: self._silhouette(i, thresholds[i], clean), range(n))):
            out.append(sil)
            if progress is not None:
                progress(i + 1, n)
        return out

    def silhouette(self, i, *, threshold=None, **clean):
        """The silhouette of view ``i`` at a threshold (grey levels; its automatic one when omitted).

        Returns
        -------
        Silhouette
        """
        if not 0 <= i < len(self):
            raise IndexError(f"view {i} out of range: {len(self)} views")
        if threshold is None:
            t = self.auto_thresholds()[i] if self.masks[i] is None else None
        else:
            t = float(threshold)
            if not t > 0:
                raise SessionError(f"threshold must be > 0 grey levels, got {t}")
        return self._silhouette(i, t, clean)

    def _silhouette(self, i, t, clean):
        if self.masks[i] is not None:
            m = self.masks[i]
            return Silhouette(m, m.astype(np.float32), None, "given")
        mask = clean_mask(self.differences[i] > t, **clean)
        if not mask.any():
            raise SessionError(
                f"{self.names[i]}: the silhouette is empty; lower --threshold or check the background frames"
            )
        return Silhouette(mask, coverage(self.images[i], self.background, mask), t, "subtraction")


def _map_views(fn, indices):
    """``[fn(i) for i in indices]`` in a few threads (the cv2, numpy and numba steps release the GIL)."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    indices = list(indices)
    workers = max(1, min(len(indices), os.cpu_count() or 1))
    if workers == 1:
        return [fn(i) for i in indices]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(fn, indices))
