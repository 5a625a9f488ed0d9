"""The threshold picker: one view's silhouette as the threshold moves."""

from __future__ import annotations

import numpy as np

from ..engine import Engine
from ..errors import SessionError
from ._common import ipywidgets, new_figure, redraw


class ThresholdPicker:
    """Pick the silhouette threshold of a session's views.

    The silhouette is what the engine's silhouette stage finds for the view
    (:attr:`organlab.engine.Engine.silhouette_model`, the
    :class:`organlab.silhouette.SilhouetteModel` of
    :func:`organlab.silhouette.silhouettes`):
    background subtraction against the session's empty frames, or keying
    against its ``backdrop``, with the picker's ``threshold`` (or, when it is
    None, the automatic threshold).

    Parameters
    ----------
    session : organlab.session.Session
        Needs ``background_images`` or a ``backdrop``.
    view : int
        Index of the view shown first.
    threshold : float or None
        In ``units``; None = automatic (subtraction: Li's, floored at 5 x
        the background noise; keying: from the border band's noise).
    mode : {'color', 'grey'}
    background : {'median', 'mean'}

    Attributes
    ----------
    view : int
    threshold : float or None
    model : organlab.silhouette.SilhouetteModel
    background : (H, W, 3) float32 or (3,) float32
        The background model, or the backdrop colour.
    floor : float
        Lowest automatic threshold (subtraction), grey levels.
    units : str
        ``'grey levels'`` or ``'Delta E'`` (a backdrop session).
    """

    def __init__(self, session, *, view=0, threshold=None, mode="color", background="median"):
        if not session.background_images and session.backdrop is None:
            raise SessionError(f"{session.json_path}: background_images: the threshold picker needs background "
                               "frames or a 'backdrop'")
        self.session = session
        self.engine = Engine(session, mode=mode, background=background)
        self.model = self.engine.silhouette_model
        self.background = self.model.background
        self.floor = self.model.floor
        self.units = self.model.units
        self._sil = {}
        self.view = view
        self.threshold = threshold
        self.controls = {}
        self.last_figure = None

    # ------------------------------------------------------------ state
    @property
    def view(self):
        return self._view

    @view.setter
    def view(self, i):
        n = len(self.session.views)
        if not (isinstance(i, (int, np.integer)) and 0 <= i < n):
            raise ValueError(f"view must be an index in [0, {n - 1}], got {i!r}")
        if self.session.views[int(i)].mask is not None:
            raise ValueError(f"view {i} has a given mask in session.json: it has no threshold to pick")
        self._view = int(i)

    @property
    def threshold(self):
        return self._threshold

    @threshold.setter
    def threshold(self, t):
        if t is not None and not float(t) > 0:
            raise ValueError(f"threshold must be > 0 {self.units} or None (automatic), got {t}")
        self._threshold = None if t is None else float(t)

    @property
    def image(self):
        """(H, W, 3) uint8: the current view's image."""
        return self.model.images[self._view]

    @property
    def difference(self):
        """(H, W) float32, in ``units``: the current view's difference to the background (or Delta E)."""
        return self.model.differences[self._view]

    @property
    def auto_threshold(self):
        """The automatic threshold of the current view, in ``units``."""
        return self.model.auto_threshold(self._view)

    @property
    def effective_threshold(self):
        """``threshold``, or ``auto_threshold`` when it is None."""
        return self.auto_threshold if self._threshold is None else self._threshold

    @property
    def silhouette(self):
        """organlab.silhouette.Silhouette of the current view at ``effective_threshold``."""
        key = (self._view, self.effective_threshold)
        if key not in self._sil:
            self._sil = {key: self.model.silhouette(self._view, threshold=key[1])}
        return self._sil[key]

    @property
    def area_px(self):
        """Pixels in the silhouette's mask."""
        return int(np.count_nonzero(self.silhouette.mask))

    @property
    def coverage_area_px(self):
        """Sum of the sub-pixel coverage, px."""
        return float(self.silhouette.coverage.sum(dtype=np.float64))

    def summary(self):
        """One line: view, threshold (and the automatic one), silhouette area."""
        t, a = self.effective_threshold, self.auto_threshold
        kind = "automatic" if self._threshold is None else "chosen"
        return (
            f"view {self._view} ({self.session.views[self._view].angle_deg:g} deg): threshold {t:.1f} ({kind}; "
            f"automatic {a:.1f}), silhouette {self.area_px} px ({100.0 * self.area_px / self.image[..., 0].size:.2f} % of the image)"
        )

    # ---------------------------------------------------------- pictures
    def figure(self):
        """The view with its mask, and the difference histogram with both thresholds; a matplotlib Figure."""
        fig = new_figure(11, 3.8)
        ax_img, ax_hist = fig.subplots(1, 2, width_ratios=[1.25, 1])
        sil = self.silhouette
        ax_img.imshow(self.image)
        overlay = np.zeros(sil.mask.shape + (4,), np.float32)
        overlay[sil.mask] = (0.1, 0.9, 0.2, 0.45)
        ax_img.imshow(overlay)
        ax_img.contour(sil.mask, levels=[0.5], colors=["lime"], linewidths=0.8)
        if sil.mask.any():  # zoom on the specimen
            rows, cols = np.nonzero(sil.mask)
            m = 0.25 * max(np.ptp(rows), np.ptp(cols)) + 10
            h, w = sil.mask.shape
            ax_img.set_xlim(max(cols.min() - m, -0.5), min(cols.max() + m, w - 0.5))
            ax_img.set_ylim(min(rows.max() + m, h - 0.5), max(rows.min() - m, -0.5))
        ax_img.set_title(f"view {self._view}: silhouette {self.area_px} px", fontsize=10)
        ax_img.set_axis_off()

        d = self.difference.ravel()
        ax_hist.hist(d, bins=128, range=(0, max(64.0, float(d.max()))), color="0.4", log=True)
        t, a = self.effective_threshold, self.auto_threshold
        ax_hist.axvline(a, color="tab:blue", ls="--", label=f"automatic {a:.1f}")
        if self._threshold is not None:
            ax_hist.axvline(t, color="tab:red", label=f"chosen {t:.1f}")
        if not self.model.keyed:
            ax_hist.axvline(self.floor, color="0.6", ls=":", label=f"noise floor {self.floor:.1f}")
        ax_hist.set_xlabel("Delta E to the backdrop" if self.model.keyed else "difference to the background (grey levels)")
        ax_hist.set_ylabel("pixels")
        ax_hist.legend(fontsize=8)
        return fig

    # ------------------------------------------------------------ widget
    def widget(self):
        """ipywidgets controls (view, threshold, automatic) over the figure; returns a VBox.

        The controls are kept in ``self.controls`` (``view``, ``threshold``,
        ``auto``, ``summary``, ``output``); setting their ``value`` from
        Python updates the picker as a person moving them would.
        The figure last drawn into the Output is ``self.last_figure``.
        """
        w = ipywidgets()
        n = len(self.session.views)
        c = self.controls = {
            "view": w.IntSlider(value=self._view, min=0, max=n - 1, description="view", continuous_update=False),
            "threshold": w.FloatSlider(
                value=round(self.effective_threshold, 1), min=0.5, max=100.0, step=0.5,
                description="threshold", continuous_update=False,
            ),
            "auto": w.Checkbox(value=self._threshold is None, description="automatic"),
            "summary": w.Label(self.summary()),
            "output": w.Output(),
        }
        syncing = []

        def refresh():
            c["summary"].value = self.summary()
            self.last_figure = redraw(c["output"], self.figure)

        def on_view(change):
            self.view = change["new"]
            if self._threshold is None:
                syncing.append(1)
                c["threshold"].value = round(self.effective_threshold, 1)
                syncing.pop()
            refresh()

        def on_threshold(change):
            if syncing:
                return
            self.threshold = change["new"]
            syncing.append(1)
            c["auto"].value = False
            syncing.pop()
            refresh()

        def on_auto(change):
            if syncing:
                return
            self.threshold = None if change["new"] else c["threshold"].value
            syncing.append(1)
            c["threshold"].value = round(self.effective_threshold, 1)
            syncing.pop()
            refresh()

        c["view"].observe(on_view, names="value")
        c["threshold"].observe(on_threshold, names="value")
        c["auto"].observe(on_auto, names="value")
        refresh()
        return w.VBox([w.HBox([c["view"], c["threshold"], c["auto"]]), c["summary"], c["output"]])
