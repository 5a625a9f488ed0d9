"""The calibration-grid checker: residuals per image, drop an image, refit."""

from __future__ import annotations

import numpy as np

from ..calibration import board_points, detect_board, fit_intrinsics
from ..errors import CalibrationError
from ._common import ipywidgets, new_figure, redraw

#: Parameters listed by :meth:`CalibrationChecker.uncertainty_rows`: (label, std key, index).
_PARAMS = (
    ("fc_x (px)", "fc", 0), ("fc_y (px)", "fc", 1), ("cc_x (px)", "cc", 0), ("cc_y (px)", "cc", 1),
    ("k1", "kc", 0), ("k2", "kc", 1), ("p1", "kc", 2), ("p2", "kc", 3),
)


def _value(camera, key, i):
    if key == "fc":
        return float(camera.K[i, i])
    if key == "cc":
        return float(camera.K[i, 2])
    return float(camera.dist[i])


class CalibrationChecker:
    """Check an intrinsic calibration image by image; drop images and refit.

    The boards are detected once (:func:`organlab.calibration.detect_board`);
    every fit is :func:`organlab.calibration.fit_intrinsics` on the detected
    corners of the images not dropped.

    Parameters
    ----------
    images : sequence of (H, W) or (H, W, 3) uint8
        The board held at varied poses.
    pattern : organlab.session.Pattern
    names : sequence of str
        One unique name per image.
    image_size : (2,) int
        ``(width, height)``, px.
    corners : dict of str to (N, 2) float64, optional
        Corners already detected (e.g. ``Calibration.intrinsics.corners``), px,
        board order; the boards are detected when omitted.
    **fit
        Options of :func:`organlab.calibration.fit_intrinsics` (``fix_k3``,
        ``estimate_skew``, ``reject_factor``, ...).

    Attributes
    ----------
    baseline : organlab.calibration.IntrinsicCalibration
        The fit with every image whose board was found.
    calibration : organlab.calibration.IntrinsicCalibration
        The fit without the dropped images.
    dropped : tuple of str
    undetected : tuple of str
        Images without a detected board.
    selected : str
        The image shown by :meth:`figure`.
    magnify : float or None
        Factor on the residual vectors in :meth:`figure`; None = automatic
        (the largest residual drawn 0.8 of a board square long).
    """

    def __init__(self, images, pattern, *, names, image_size, corners=None, **fit):
        images = list(images)
        names = [str(n) for n in names]
        if len(names) != len(images) or len(set(names)) != len(names):
            raise CalibrationError("names must hold one unique name per image")
        self.pattern = pattern
        self.image_size = tuple(int(s) for s in image_size)
        self._fit_options = dict(fit)
        self.images = dict(zip(names, images))
        if corners is not None:
            unknown = sorted(set(map(str, corners)) - set(names))
            if unknown:
                raise CalibrationError(f"corners given for images not among the names: {unknown}")
            self.corners = {n: np.asarray(corners[n], np.float64).reshape(-1, 2) for n in names if n in corners}
        else:
            self.corners = {}
            for n, img in self.images.items():
                c = detect_board(img, pattern)
                if c is not None:
                    self.corners[n] = c
        self.undetected = tuple(n for n in names if n not in self.corners)
        self.baseline = fit_intrinsics(self.corners, pattern, image_size=self.image_size, **fit)
        self.calibration = self.baseline
        self.dropped = ()
        self.selected = next(iter(self.corners)) if self.corners else names[0]
        self.magnify = None
        self.controls = {}
        self.last_figure = None

    @classmethod
    def from_session(cls, session, *, calibration=None, **fit):
        """The checker of a session's ``calibration.intrinsic_images``.

        ``calibration``: an :class:`organlab.calibration.Calibration` of the
        session whose intrinsic fit's detected corners are reused (no new detection).
        """
        if not session.intrinsic_images:
            raise CalibrationError(f"{session.json_path}: calibration.intrinsic_images: none to check")
        images = [
            session.read(p, key=f"calibration.intrinsic_images[{i}]", grey=True)
            for i, p in enumerate(session.intrinsic_images)
        ]
        names = [session.relpath(p) for p in session.intrinsic_images]
        corners = None
        if calibration is not None and calibration.intrinsics is not None:
            corners = calibration.intrinsics.corners
        return cls(images, session.pattern, names=names, image_size=session.image_size, corners=corners, **fit)

    # ------------------------------------------------------------ state
    @property
    def names(self):
        return tuple(self.images)

    def set_dropped(self, names):
        """Drop exactly ``names`` (the others are used) and refit.

        Raises
        ------
        CalibrationError
            An unknown name, or too few images left to fit (the previous fit is kept).
        """
        names = tuple(dict.fromkeys(str(n) for n in names))
        unknown = [n for n in names if n not in self.images]
        if unknown:
            raise CalibrationError(f"unknown image(s) {unknown}; the images are {list(self.images)}")
        used = {n: c for n, c in self.corners.items() if n not in names}
        self.calibration = fit_intrinsics(used, self.pattern, image_size=self.image_size, **self._fit_options)
        self.dropped = names

    def drop(self, name):
        """Leave image ``name`` out and refit."""
        self.set_dropped(self.dropped + (str(name),))

    def restore(self, name):
        """Use image ``name`` again and refit."""
        self.set_dropped(tuple(n for n in self.dropped if n != str(name)))

    def status(self, name):
        """``'used'``, ``'dropped'``, ``'rejected'`` (by the fit's outlier test) or ``'no board'``."""
        if name in self.dropped:
            return "dropped"
        if name in self.calibration.per_image_rms:
            return "used"
        if name in self.corners:
            return "rejected"
        return "no board"

    def residuals(self, name):
        """Detected and reprojected corners of an image under the current fit.

        Returns
        -------
        detected : (N, 2) float64 or None
            Pixels ``(u, v)``; None when no board was found.
        reprojected : (N, 2) float64 or None
            The board's corners through the fitted camera and the image's
            fitted board pose; None when the image is not in the fit.
        """
        import cv2

        det = self.corners.get(name)
        ext = self.calibration.extrinsics.get(name)
        if det is None or ext is None:
            return det, None
        cam = self.calibration.camera.with_pose(cv2.Rodrigues(np.asarray(ext[0], float))[0], ext[1])
        return det, cam.project(board_points(self.pattern))

    def uncertainty_rows(self):
        """Each parameter with its three-sigma uncertainty before (all images) and after (without the dropped).

        Returns
        -------
        list of dict
            ``parameter``, ``before``, ``before_3sigma``, ``after``, ``after_3sigma``.
        """
        rows = []
        b, a = self.baseline, self.calibration
        for label, key, i in _PARAMS:
            rows.append({
                "parameter": label,
                "before": _value(b.camera, key, i),
                "before_3sigma": float(np.ravel(b.uncertainty[key])[i]),
                "after": _value(a.camera, key, i),
                "after_3sigma": float(np.ravel(a.uncertainty[key])[i]),
            })
        return rows

    def uncertainty_html(self):
        """:meth:`uncertainty_rows` and the RMS of both fits as an HTML table."""
        head = (
            "<tr><th>parameter</th><th>all images</th><th>"
            + (f"without {', '.join(self.dropped)}" if self.dropped else "current fit")
            + "</th></tr>"
        )
        body = "".join(
            f"<tr><td>{r['parameter']}</td><td>{r['before']:.5g} &plusmn; {r['before_3sigma']:.2g}</td>"
            f"<td>{r['after']:.5g} &plusmn; {r['after_3sigma']:.2g}</td></tr>"
            for r in self.uncertainty_rows()
        )
        rms = (
            f"<tr><td>RMS (px)</td><td>{self.baseline.rms_px:.4f} ({len(self.baseline.per_image_rms)} images)</td>"
            f"<td>{self.calibration.rms_px:.4f} ({len(self.calibration.per_image_rms)} images)</td></tr>"
        )
        return f"<table>{head}{body}{rms}</table><small>&plusmn; three standard deviations (Bouguet's convention)</small>"

    # ---------------------------------------------------------- pictures
    def _magnify_for(self, det, rep):
        if self.magnify is not None:
            return float(self.magnify)
        worst = float(np.max(np.linalg.norm(rep - det, axis=1)))
        spacing = float(np.median(np.linalg.norm(np.diff(det, axis=0), axis=1)))
        return max(1.0, round(0.8 * spacing / max(worst, 1e-6), -1))

    def figure(self, name=None):
        """The image with detected (+) and reprojected (o) corners and magnified residuals, and per-image RMS bars."""
        name = self.selected if name is None else str(name)
        if name not in self.images:
            raise CalibrationError(f"unknown image {name!r}; the images are {list(self.images)}")
        fig = new_figure(12, 4.2)
        ax_img, ax_bar = fig.subplots(1, 2, width_ratios=[1.3, 1])
        ax_img.imshow(self.images[name], cmap="gray")
        det, rep = self.residuals(name)
        title = f"{name}: {self.status(name)}"
        if det is not None:
            ax_img.plot(det[:, 0], det[:, 1], "+", color="lime", ms=7, label="detected")
        if rep is not None:
            m = self._magnify_for(det, rep)
            ax_img.plot(rep[:, 0], rep[:, 1], "o", mfc="none", color="red", ms=6, label="reprojected")
            r = rep - det
            ax_img.quiver(det[:, 0], det[:, 1], m * r[:, 0], m * r[:, 1], color="yellow", angles="xy",
                          scale_units="xy", scale=1.0, width=0.004, label=f"residual x {m:g}")
            title += f", RMS {self.calibration.per_image_rms[name]:.3f} px"
        if det is not None:  # zoom on the board
            spacing = float(np.median(np.linalg.norm(np.diff(det, axis=0), axis=1)))
            lo, hi = det.min(axis=0) - 1.5 * spacing, det.max(axis=0) + 1.5 * spacing
            ax_img.set_xlim(max(lo[0], -0.5), min(hi[0], self.image_size[0] - 0.5))
            ax_img.set_ylim(min(hi[1], self.image_size[1] - 0.5), max(lo[1], -0.5))
        ax_img.set_title(title, fontsize=10)
        ax_img.legend(fontsize=8, loc="lower right")
        ax_img.set_axis_off()

        names = list(self.images)
        colors = {"used": "tab:blue", "dropped": "0.75", "rejected": "tab:red", "no board": "white"}
        vals = [self.calibration.per_image_rms.get(n, self.baseline.per_image_rms.get(n, 0.0)) for n in names]
        bars = ax_bar.barh(range(len(names)), vals, color=[colors[self.status(n)] for n in names], edgecolor="k")
        bars[names.index(name)].set_linewidth(2.5)
        ax_bar.axvline(self.calibration.rms_px, color="k", ls="--", lw=1, label=f"fit RMS {self.calibration.rms_px:.3f} px")
        ax_bar.set_yticks(range(len(names)), [n.rsplit("/", 1)[-1] for n in names], fontsize=7)
        ax_bar.invert_yaxis()
        ax_bar.set_xlabel("reprojection RMS (px); grey: dropped (value of the fit with all images)")
        ax_bar.legend(fontsize=8)
        return fig

    # ------------------------------------------------------------ widget
    def widget(self):
        """ipywidgets controls: image picker, magnification, drop/restore button, uncertainty table; a VBox.

        The controls are kept in ``self.controls`` (``image``, ``magnify``,
        ``drop``, ``table``, ``output``); ``controls["drop"].click()`` drops
        (or restores) the selected image as a person's click would.
        The figure last drawn into the Output is ``self.last_figure``.
        """
        w = ipywidgets()
        c = self.controls = {
            "image": w.Dropdown(options=list(self.images), value=self.selected, description="image"),
            "magnify": w.FloatLogSlider(value=self.magnify or 100.0, min=0, max=4, description="magnify",
                                        continuous_update=False),
            "auto_magnify": w.Checkbox(value=self.magnify is None, description="automatic magnification"),
            "drop": w.Button(description="drop / restore"),
            "table": w.HTML(self.uncertainty_html()),
            "message": w.Label(""),
            "output": w.Output(),
        }

        def refresh():
            c["drop"].description = "restore this image" if self.selected in self.dropped else "drop this image"
            c["table"].value = self.uncertainty_html()
            self.last_figure = redraw(c["output"], self.figure)

        def on_image(change):
            self.selected = change["new"]
            refresh()

        def on_magnify(_change):
            self.magnify = None if c["auto_magnify"].value else c["magnify"].value
            refresh()

        def on_drop(_button):
            try:
                if self.selected in self.dropped:
                    self.restore(self.selected)
                else:
                    self.drop(self.selected)
                c["message"].value = ""
            except CalibrationError as e:
                c["message"].value = f"not refitted: {e}"
            refresh()

        c["image"].observe(on_image, names="value")
        c["magnify"].observe(on_magnify, names="value")
        c["auto_magnify"].observe(on_magnify, names="value")
        c["drop"].on_click(on_drop)
        refresh()
        controls = w.HBox([c["image"], c["drop"], c["magnify"], c["auto_magnify"]])
        return w.VBox([controls, c["message"], w.HBox([c["output"], c["table"]])])
