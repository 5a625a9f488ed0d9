"""The carving tuner: voxel size, tolerance and colour threshold against volume and agreement."""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import Camera
from ..engine import METHODS, Engine, Settings, color_threshold_range
from ..errors import OrganlabError
from ..figures import mesh_snapshot
from ..session import Session
from ..silhouette import Silhouette
from ._common import ipywidgets, new_figure, redraw


class CarvingTuner:
    """Carve a session with chosen parameters and report what they give.

    Each :meth:`run` is a run of one :class:`organlab.engine.Engine` (the
    stages of :func:`organlab.pipeline.reconstruct`: the hull field of the
    sub-pixel silhouettes, optionally voxel colouring of the hull, the
    marching-cubes surface, the view agreement), kept across runs: a new
    voxel size re-runs the carving onward, a new colour threshold only the
    colouring onward.  The surface is not finished (``finish=False``): the
    tuner compares carving parameters, quickly.

    Parameters
    ----------
    images : sequence of (H, W, 3) uint8
        The views (used by the colour test).
    silhouettes : sequence of organlab.silhouette.Silhouette
        One per view.
    cameras : sequence of organlab.camera.Camera
        One per view.
    roi_min, roi_max : (3,) float, mm, world frame
        The box carved.
    voxel_size : float, mm
    tolerance : int
        Views allowed to disagree before a voxel is carved.
    color_threshold : float, 'auto' or None
        Photo-consistency threshold in the unit of ``method``
        (:func:`organlab.engine.color_threshold_range`: grey levels, or
        the NCC gain for ``'photo'``), ``'auto'`` for the automatic one
        (measured from the image noise; ``'photo'``'s default gain), None =
        no colour test.  The colour test runs as ``organlab reconstruct`` runs it
        (:data:`organlab.coloring.PIPELINE_OPTIONS`: exposure, shading
        measure, automatic support, silhouette guard), so a low threshold
        widens the support instead of digging through the specimen.
    method : {'coloring', 'space_carving', 'photo'}
        The colouring method of the colour test (the engine's
        ``Settings.method``); ``'photo'`` is the one for textured specimens.
    reference_volume : float, optional
        The specimen's true volume, mm^3, to report the error against.
    angles_deg : sequence of float, optional
        Table angle of each view, for the agreement plot's axis.

    Attributes
    ----------
    result : dict or None
        After :meth:`run`: ``grid``, ``occupancy``, ``mesh``, ``volume_mm3``
        (the mesh's), ``voxel_volume_mm3``, ``agreement`` ((n_views,) IoU of
        each silhouette with the model's silhouette in that view),
        ``coloring`` (the colouring's report entry or None), ``color_threshold``
        (the threshold used, the measured one for ``'auto'``; or None),
        ``error_pct`` (or None), ``reconstruction`` (the engine's
        :class:`organlab.engine.Reconstruction`).
    engine : organlab.engine.Engine
    """

    def __init__(self, images: Sequence[np.ndarray], silhouettes: Sequence[Silhouette], cameras: Sequence[Camera],
                 roi_min: Sequence[float], roi_max: Sequence[float], *, voxel_size: float = 2.0, tolerance: int = 0,
                 color_threshold: float | str | None = None, method: str = "coloring",
                 reference_volume: float | None = None, angles_deg: Sequence[float] | None = None):
        n = len(cameras)
        if len(silhouettes) != n or len(images) != n:
            raise OrganlabError(f"got {len(images)} images, {len(silhouettes)} silhouettes and {n} cameras: need one of each per view")
        self.images = list(images)
        self.silhouettes = list(silhouettes)
        self.cameras = list(cameras)
        self.roi_min = np.asarray(roi_min, np.float64)
        self.roi_max = np.asarray(roi_max, np.float64)
        self.voxel_size = float(voxel_size)
        self.tolerance = int(tolerance)
        if not (color_threshold is None or (isinstance(color_threshold, str) and color_threshold == "auto")
                or (not isinstance(color_threshold, bool) and isinstance(color_threshold, (int, float))
                    and color_threshold > 0)):
            raise OrganlabError(f"color_threshold must be a number > 0, 'auto' or None, got {color_threshold!r}")
        if method not in METHODS[1:]:  # the engine's colouring methods (all but 'hull')
            raise OrganlabError(f"method must be one of {', '.join(map(repr, METHODS[1:]))}, got {method!r}")
        self.color_threshold = color_threshold
        self.method = method
        self.reference_volume = reference_volume
        self.angles_deg = None if angles_deg is None else [float(a) for a in angles_deg]
        self.engine = Engine.from_views(self.images, self.silhouettes, self.cameras)
        self.result = None
        self.controls = {}
        self.last_figure = None

    @classmethod
    def from_session(cls, session: Session, cameras: Sequence[Camera], silhouettes: Sequence[Silhouette] | None = None,
                     *, views: Sequence[int] | None = None, **options: Any) -> CarvingTuner:
        """The tuner of a session with its cameras (e.g. from the calibration).

        ``views``: indices of the views to use (default all); silhouettes are
        the engine's silhouette stage (automatic thresholds) when not given.
        """
        idx = list(range(len(session.views))) if views is None else [int(i) for i in views]
        engine = Engine(session, views=idx, cameras=[cameras[i] for i in idx])
        if silhouettes is None:
            sils = engine.run(Settings(), until="silhouettes").silhouettes
        else:
            sils = [silhouettes[i] for i in idx]
        options.setdefault("reference_volume", session.reference.get("volume_mm3"))
        options.setdefault("angles_deg", [session.views[i].angle_deg for i in idx])
        return cls(engine.images, sils, [cameras[i] for i in idx], session.roi_min, session.roi_max, **options)

    # ------------------------------------------------------------- run
    def settings(self) -> Settings:
        """The engine's settings of the current parameters."""
        t = self.color_threshold
        return Settings(voxel_size=self.voxel_size, tolerance=self.tolerance, finish=False, measure=False,
                        method="hull" if t is None else self.method, color_threshold=None if t in (None, "auto") else float(t),
                        roi=(tuple(map(float, self.roi_min)), tuple(map(float, self.roi_max))))

    def run(self) -> dict:
        """Carve with the current parameters; returns (and keeps) ``result``."""
        rec = self.engine.run(self.settings())
        ref = self.reference_volume
        volume = float(rec.mesh.volume)
        self.result = {
            "grid": rec.grid,
            "occupancy": rec.occupancy,
            "mesh": rec.mesh,
            "volume_mm3": volume,
            "voxel_volume_mm3": rec.grid.volume_of(rec.occupancy),
            "agreement": np.asarray(rec.agreement.iou),
            "coloring": rec.coloring,
            "color_threshold": rec.color_threshold,
            "error_pct": None if not ref else 100.0 * (volume - ref) / ref,
            "reconstruction": rec,
        }
        return self.result

    def summary(self) -> str:
        """One line: parameters, volume, error, worst agreement."""
        r = self.result if self.result is not None else self.run()
        text = (
            f"{self.voxel_size:g} mm voxels, tolerance {self.tolerance}, colour test "
            + ("off" if r["color_threshold"] is None else
               f"{r['color_threshold']:.{self._digits()}f}" + (" (automatic)" if self.color_threshold == "auto" else ""))
            + f": mesh volume {r['volume_mm3'] / 1000:.2f} cm3"
        )
        if r["error_pct"] is not None:
            text += f" ({r['error_pct']:+.2f} % vs reference)"
        return text + f", agreement (IoU) worst view {r['agreement'].min():.3f}, mean {r['agreement'].mean():.3f}"

    def _digits(self) -> int:
        """Decimals that show a colour threshold in its unit (grey levels 1, an NCC gain 2)."""
        return 1 if color_threshold_range(self.method).step >= 0.1 else 2

    # ---------------------------------------------------------- pictures
    def mesh_picture(self, *, window_size: tuple = (640, 560)) -> np.ndarray:
        """(H, W, 3) uint8: the mesh rendered off-screen (pyvista, :func:`organlab.figures.mesh_snapshot`)."""
        from matplotlib.image import imread

        r = self.result if self.result is not None else self.run()
        with tempfile.TemporaryDirectory() as d:
            path = mesh_snapshot(r["mesh"], Path(d) / "mesh.png", window_size=window_size)
            return (imread(path)[..., :3] * 255).astype(np.uint8)

    def figure(self):
        """The mesh picture and the per-view agreement bars; a matplotlib Figure."""
        r = self.result if self.result is not None else self.run()
        fig = new_figure(11, 4.2)
        ax_mesh, ax_bar = fig.subplots(1, 2, width_ratios=[1, 1.2])
        ax_mesh.imshow(self.mesh_picture())
        ax_mesh.set_axis_off()
        title = f"{r['volume_mm3'] / 1000:.2f} cm3"
        if r["error_pct"] is not None:
            title += f" ({r['error_pct']:+.2f} %)"
        ax_mesh.set_title(title, fontsize=10)
        ag = r["agreement"]
        ax_bar.bar(np.arange(len(ag)), ag, color="tab:green")
        ax_bar.set_ylim(max(0.0, float(ag.min()) - 0.05), 1.0)
        if self.angles_deg is not None:
            ax_bar.set_xticks(np.arange(len(ag)), [f"{a:g}" for a in self.angles_deg], fontsize=8)
            ax_bar.set_xlabel("view (table angle, deg)")
        else:
            ax_bar.set_xlabel("view")
        ax_bar.set_ylabel("IoU of silhouette and model's silhouette")
        ax_bar.set_title(self.summary().split(": ", 1)[0], fontsize=9)
        return fig

    # ------------------------------------------------------------ widget
    def widget(self):
        """ipywidgets controls (voxel size, tolerance, colour test and threshold) over the figure; a VBox.

        The controls are kept in ``self.controls`` (``voxel_size``,
        ``tolerance``, ``color``, ``color_auto``, ``color_threshold``,
        ``summary``, ``output``); setting a ``value`` re-runs the carving.
        With ``color_auto`` ticked the slider shows the measured threshold;
        moving it unticks ``color_auto``.
        The figure last drawn into the Output is ``self.last_figure``.
        """
        w = ipywidgets()
        auto = self.color_threshold == "auto"
        rng = color_threshold_range(self.method)  # the slider's bounds, step and unit for this method
        start = 18.0 if rng.default is None else rng.default  # where the slider rests before a run
        c = self.controls = {
            "voxel_size": w.FloatSlider(value=self.voxel_size, min=1.0, max=6.0, step=0.5, description="voxel (mm)",
                                        continuous_update=False),
            "tolerance": w.IntSlider(value=self.tolerance, min=0, max=max(1, min(4, len(self.cameras) - 1)),
                                     description="tolerance", continuous_update=False),
            "color": w.Checkbox(value=self.color_threshold is not None, description="colour test"),
            "color_auto": w.Checkbox(value=self.color_threshold is None or auto, description="automatic"),
            "color_threshold": w.FloatSlider(value=start if self.color_threshold in (None, "auto") else self.color_threshold,
                                             min=rng.low, max=rng.high, step=rng.step, description="colour thr.",
                                             continuous_update=False),
            "summary": w.Label(""),
            "output": w.Output(),
        }
        syncing = []

        def refresh(change=None):
            if syncing:
                return
            if change is not None and change["owner"] is c["color_threshold"]:
                syncing.append(1)
                c["color_auto"].value = False  # a threshold moved by hand is a chosen one
                syncing.pop()
            self.voxel_size = c["voxel_size"].value
            self.tolerance = c["tolerance"].value
            self.color_threshold = (None if not c["color"].value else
                                    "auto" if c["color_auto"].value else c["color_threshold"].value)
            try:
                self.run()
                c["summary"].value = self.summary()
            except OrganlabError as e:
                c["summary"].value = f"error: {e}"
                return
            if self.result["color_threshold"] is not None and self.color_threshold == "auto":
                syncing.append(1)  # the slider shows the measured threshold
                c["color_threshold"].value = round(self.result["color_threshold"] / rng.step) * rng.step
                syncing.pop()
            self.last_figure = redraw(c["output"], self.figure)

        for k in ("voxel_size", "tolerance", "color", "color_auto", "color_threshold"):
            c[k].observe(refresh, names="value")
        refresh()
        return w.VBox([w.HBox([c["voxel_size"], c["tolerance"]]),
                       w.HBox([c["color"], c["color_auto"], c["color_threshold"]]), c["summary"], c["output"]])
