"""The viewer's GUI panel: controls that re-run, read-outs, views, carve by view, roi."""

from __future__ import annotations

import math
import threading

import numpy as np

from ..engine import HULL_METHODS, METHODS, color_threshold_range
from ..errors import OrganlabError
from ..preflight import check_grid_memory
from . import _scene

MODELS = ("mesh", "voxels", "mesh + voxels")
#: Bounds of the controls, enforced on the server: viser does not enforce a slider's limits, and a
#: crafted message set a 0.05 mm voxel or a 3 m roi (30-45 s at 2.8 GB while newer requests waited).
THRESHOLD_RANGE = (1.0, 80.0)
VOXEL_RANGE = (0.5, 5.0)
ROI_SIDE_RANGE = (1.0, 1000.0)  # mm


class Controls:
    """Build the GUI of a :class:`SessionViewer` and wire its callbacks."""

    def __init__(self, app):
        self.app = app
        self.live = app.live
        gui = app.live.server.gui
        self.gui = gui
        self._lock = threading.Lock()
        self._local = threading.local()  # .quiet: this thread is showing a value the user did not set
        st = app.settings
        auto = app.auto_threshold
        n = len(app.cameras)

        with gui.add_folder("Reconstruction"):
            self.status = gui.add_markdown("*starting*")
            keyed = app.threshold_units == "Delta E"
            t0 = round(auto * 2) / 2 if auto is not None else 20.0
            self.threshold = gui.add_slider(
                "Threshold", min=1.0, max=80.0, step=0.5, initial_value=t0,
                marks=((t0, "auto"),) if auto is not None else None, disabled=auto is None,
                hint=("silhouette threshold, Delta E (CIE Lab) from the backdrop" if keyed else
                      "silhouette threshold, grey levels") + " (the mark: median of the automatic per-view values)",
            )
            self.auto = gui.add_checkbox(
                "Automatic threshold", initial_value=True, disabled=auto is None,
                hint="per view: above the noise of the image border and of the background next to the specimen, "
                "at most Li's" if keyed else
                "Li's automatic threshold, per view, at least 5 x the background frames' noise")
            self.voxel = gui.add_slider("Voxel size (mm)", min=0.5, max=5.0, step=0.5, initial_value=st.voxel_size)
            self.method = gui.add_dropdown("Method", METHODS, initial_value=st.method)
            self.hull = gui.add_dropdown("Hull", HULL_METHODS, initial_value=st.hull)
            rng = color_threshold_range("coloring" if st.method == "hull" else st.method)
            self._color_method = "coloring" if st.method == "hull" else st.method
            self.color_threshold = gui.add_slider(
                "Colour threshold", min=rng.low, max=rng.high, step=rng.step,
                initial_value=rng.default if rng.default is not None else rng.low, disabled=True,
                hint="photo-consistency threshold (grey levels; for photo the NCC gain); shows the automatic one "
                     "until moved")
            self.color_auto = gui.add_checkbox("Automatic colour threshold", initial_value=True, disabled=True,
                                               hint="from the measured image noise (organlab.coloring)")
            self.tolerance = gui.add_slider("Tolerance (views)", min=0, max=min(5, n - 1), step=1, initial_value=0)
            self.rerun_button = gui.add_button("Re-run")
        with gui.add_folder("Measurements"):
            self.measure = gui.add_markdown("*no result yet*")
        with gui.add_folder("Views"):
            self.view = gui.add_slider("View", min=0, max=max(n - 1, 1), step=1, initial_value=0)
            self.look = gui.add_button("Look through camera")
            self.leave = gui.add_button("Leave camera view")
            self.view_info = gui.add_markdown("")
            self.view_image = gui.add_image(np.zeros((48, 64, 3), np.uint8), label="photo, silhouette, hull")
        with gui.add_folder("Carve by view", expand_by_default=False):
            self.carve_show = gui.add_checkbox("Show carved space", initial_value=False)
            self.carve_step = gui.add_slider("Step (-1: all views)", min=-1, max=max(n - 1, 0), step=1, initial_value=-1)
            self.carve_info = gui.add_markdown("")
        with gui.add_folder("Region of interest", expand_by_default=False):
            self.roi_edit = gui.add_checkbox("Edit roi (drag the gizmo)", initial_value=False)
            lo, hi = (np.asarray(v, float) for v in st.roi)
            self.roi_size = gui.add_vector3("Size (mm)", initial_value=tuple(hi - lo), min=(1.0, 1.0, 1.0), step=1.0)
            self.roi_info = gui.add_markdown("")
            self.roi_apply = gui.add_button("Apply roi and re-run")
        with gui.add_folder("Display"):
            self.model = gui.add_dropdown("Model", MODELS, initial_value="mesh",
                                          hint="the carved surface voxels, the mesh, or both")
            self.show_views_box = gui.add_checkbox("Cameras", initial_value=True)
            self.aaa_box = gui.add_checkbox("AAA measures", initial_value=True, disabled=not app.is_aaa,
                                            hint="centreline, maximum-diameter section (the mesh translucent)")
        self._roi_box = None
        self._roi_gizmo = None
        self._roi_centre = (lo + hi) / 2
        self._update_roi_info()
        self._wire()

    # ------------------------------------------------------------ wiring
    @property
    def show_mesh(self):
        return "mesh" in self.model.value

    @property
    def show_voxels(self):
        return "voxels" in self.model.value

    @property
    def show_aaa(self):
        return bool(self.aaa_box.value)

    def _settings_changed(self, **changes):
        """Re-run with ``changes``, after the grid memory pre-flight of what it would build."""
        lo, hi = changes["roi"] if "roi" in changes else self.roi()
        vs = changes.get("voxel_size", self._bounded(self.voxel, *VOXEL_RANGE))
        tol = changes.get("tolerance", self._bounded(self.tolerance, 0, self._max_tolerance, integer=True))
        try:
            check_grid_memory(lo, hi, vs, tolerance=tol, where="viewer")
        except OrganlabError as e:
            self.show_status(f"not run: {e}")
            return
        self.app.rerun(**changes)

    @property
    def _max_tolerance(self):
        return max(0, min(5, len(self.app.cameras) - 1))

    def _bounded(self, handle, lo, hi, *, integer=False):
        """The control's value within ``[lo, hi]`` (finite; an int with ``integer``); shown corrected when it was not."""
        v = handle.value
        try:
            x = float(v)
        except (TypeError, ValueError):
            x = lo
        x = min(max(x if math.isfinite(x) else lo, lo), hi)
        if integer:
            x = int(round(x))
        if x != v:
            self._set_quietly(handle, x)
        return x

    def _color_bounds(self):
        rng = color_threshold_range(self._color_method)
        return rng.low, rng.high

    def _color_range(self, method):
        """Give the colour slider ``method``'s range, step and automatic value (from the engine); True when
        its unit changed (grey levels <-> NCC gain).  ``'hull'`` keeps the slider as it is."""
        if method == "hull" or method == self._color_method:
            return False
        old, rng = color_threshold_range(self._color_method), color_threshold_range(method)
        self._color_method = method
        h = self.color_threshold
        value = rng.default if rng.default is not None else min(max(h.value, rng.low), rng.high)
        h.min, h.max, h.step, h.precision = rng.low, rng.high, rng.step, 2 if rng.step < 0.1 else 1
        self._set_quietly(h, value)
        return old.unit != rng.unit

    def _choice(self, handle, options):
        """The dropdown's value when it is one of ``options``, else the first (shown corrected)."""
        if handle.value not in options:
            self._set_quietly(handle, options[0])
        return handle.value

    def _roi_size(self):
        size = self.roi_size.value
        try:
            v = np.asarray(size, dtype=np.float64).reshape(3)
        except (TypeError, ValueError):
            v = np.full(3, 100.0)
        v = np.clip(np.where(np.isfinite(v), v, ROI_SIDE_RANGE[0]), *ROI_SIDE_RANGE)
        if tuple(v) != tuple(size):
            self._set_quietly(self.roi_size, tuple(float(x) for x in v))
        return v

    def _wire(self):
        app = self.app

        @self.threshold.on_update
        def _(_e):
            if self._quiet:
                return
            t = self._bounded(self.threshold, *THRESHOLD_RANGE)
            self.auto.value = False
            self._settings_changed(threshold=t)

        @self.auto.on_update
        def _(_e):
            self._settings_changed(threshold=None if self.auto.value else self._bounded(self.threshold, *THRESHOLD_RANGE))

        @self.voxel.on_update
        def _(_e):
            if self._quiet:
                return
            vs = self._bounded(self.voxel, *VOXEL_RANGE)
            self._update_roi_info()
            self._settings_changed(voxel_size=vs)

        @self.method.on_update
        def _(_e):
            if self._quiet:
                return
            method = self._choice(self.method, METHODS)
            self.color_threshold.disabled = self.color_auto.disabled = method == "hull"
            if self._color_range(method):  # another unit: a chosen threshold means nothing there
                self._set_quietly(self.color_auto, True)
                self._settings_changed(method=method, color_threshold=None)
            else:
                self._settings_changed(method=method)

        @self.hull.on_update
        def _(_e):
            if not self._quiet:
                self._settings_changed(hull=self._choice(self.hull, HULL_METHODS))

        @self.color_threshold.on_update
        def _(_e):
            if self._quiet:
                return
            self._set_quietly(self.color_auto, False)
            self._settings_changed(color_threshold=self._bounded(self.color_threshold, *self._color_bounds()))

        @self.color_auto.on_update
        def _(_e):
            if not self._quiet:
                self._settings_changed(color_threshold=None if self.color_auto.value else
                                       self._bounded(self.color_threshold, *self._color_bounds()))

        @self.tolerance.on_update
        def _(_e):
            if self._quiet:
                return
            tol = self._bounded(self.tolerance, 0, self._max_tolerance, integer=True)
            self._update_roi_info()
            self._settings_changed(tolerance=tol)

        @self.rerun_button.on_click
        def _(_e):
            app.rerun()

        self._wire_views()

    def _wire_views(self):
        @self.view.on_update
        def _(_e):
            if not self._quiet:
                self.select(self._view_index())

        @self.look.on_click
        def _(e):
            self.look_through(self._view_index(), e.client)

        @self.leave.on_click
        def _(_e):
            self.live.hide_look()

        @self.live.on_view_click
        def _(i, client):
            self.view.value = i  # fires select()
            self.look_through(i, client)

        @self.carve_show.on_update
        def _(_e):
            self._carve_display()

        @self.carve_step.on_update
        def _(_e):
            if self._quiet:
                return
            self._bounded(self.carve_step, -1, max(len(self.app.cameras) - 1, 0), integer=True)
            if self.carve_show.value:
                self._carve_display()

        @self.roi_edit.on_update
        def _(_e):
            self._roi_gizmo_toggle(self.roi_edit.value)

        @self.roi_size.on_update
        def _(_e):
            if self._quiet:
                return
            self._roi_size()
            self._update_roi_box()

        @self.roi_apply.on_click
        def _(_e):
            lo, hi = self.roi()
            self._settings_changed(roi=(tuple(lo), tuple(hi)))

        @self.model.on_update
        def _(_e):
            self._choice(self.model, MODELS)
            self.live.set_visible("mesh", self.show_mesh)
            self.live.set_visible("voxels", self.show_voxels)

        @self.show_views_box.on_update
        def _(_e):
            self.live.set_visible("views", bool(self.show_views_box.value))

        @self.aaa_box.on_update
        def _(_e):
            res = self.app.result
            if res is not None:
                self.app._show_surface(res.mesh, res.aaa)

    @property
    def _quiet(self):
        return getattr(self._local, "quiet", False)

    def _set_quietly(self, handle, value):
        """Show ``value`` in a control without re-running: viser calls on_update for server-side sets too,
        synchronously in the setting thread (so the flag is per thread)."""
        self._local.quiet = True
        try:
            handle.value = value
        finally:
            self._local.quiet = False

    # ------------------------------------------------------------ read-outs
    def show_status(self, text):
        self.status.content = f"*{text}*"

    def views_added(self):
        self.select(self._view_index())

    def show_result(self, res):
        mesh = res.mesh
        vol = res.grid.volume_of(res.occupancy)
        ag = res.agreement
        lines = [
            f"**Volume** {mesh.volume / 1000:.2f} cm³ (voxels {vol / 1000:.2f} cm³)",
            f"**Area** {mesh.area / 100:.2f} cm²",
            f"**Watertight** {'yes' if mesh.is_watertight else 'NO'}",
            f"**Surface voxels** {res.n_surface_voxels:,} at {res.grid.voxel_size:g} mm",
        ]
        if res.aaa is not None:
            a = res.aaa
            lines.append(f"**AAA max diameter** {a.max_diameter_mm:.1f} mm (equivalent {a.max_equivalent_mm:.1f} mm) "
                         f"at z {a.max_location_mm[2]:.1f} mm; neck {a.neck_diameter_mm:.1f} mm, "
                         f"sac {a.sac_length_mm:.0f} mm, {a.sac_volume_mm3 / 1000:.1f} cm³")
        elif res.aaa_error is not None:
            lines.append(f"**AAA** not measured: {res.aaa_error}")
        fig = res.figures
        if fig is not None and len(fig.iou):  # the figures and ranking of report.json and the CLI summary
            ids = self.app.view_ids
            lines.append("**Agreement** " + fig.line(lambda j: f"{ids[j]} ({fig.names[j]})"))
            lines.append("<br/>" + " ".join(f"`{ids[j]}:{a:.2f}`" for j, a in enumerate(ag)))
        if res.color_threshold is not None:
            self._color_range(res.settings.method)  # a re-run asked for by code (app.rerun) may change method
            rng = color_threshold_range(self._color_method)
            digits = 2 if rng.step < 0.1 else 1
            lines.append(f"**Colour threshold** {res.color_threshold:.{digits}f}"
                         + (f" {rng.unit}" if rng.default is not None else "")
                         + (" (automatic)" if res.settings.color_threshold is None else ""))
            if res.settings.color_threshold is None:  # the slider shows the threshold colouring measured
                self._set_quietly(self.color_threshold, round(res.color_threshold / rng.step) * rng.step)
        warnings = (getattr(res, "report", None) or {}).get("warnings", [])
        if warnings:  # the run's own warnings, as organlab reconstruct prints them
            lines.insert(0, "**Warnings** " + "<br/>".join(f"⚠ {w}" for w in warnings))
        self.measure.content = "  \n".join(lines)
        self.show_status(self.app.status)
        self.select(self._view_index())
        if self.carve_show.value:
            self._carve_display()

    # ------------------------------------------------------------ views
    def select(self, j):
        app = self.app
        if j >= len(self.live.cameras):
            return
        hull = app.hull_in_view(j)
        img = self.live.select_view(j, hull)
        self.view_image.image = _scene.thumbnail(img, 320)
        ag = None if app.result is None or app.result.agreement is None else app.result.agreement[j]
        angle = app.session.views[app.view_ids[j]].angle_deg
        text = f"view **{app.view_ids[j]}**" + (f" at {angle:g}°" if angle is not None else "")
        if ag is not None:
            text += f": agreement (IoU of hull and silhouette) **{ag:.3f}**"
        self.view_info.content = text
        return img

    def look_through(self, j, client=None):
        img = self.select(j)
        self.live.look_through(j, client, image=img)

    # ------------------------------------------------------------ carve by view
    def _carve_display(self):
        if not self.carve_show.value:
            self.live.set_visible("carved", False)
            self.carve_info.content = ""
            return
        views = self.app.carving_views()
        if views is None:
            return
        res = self.app.result
        if self.live._carved is None or getattr(self, "_carved_for", None) is not res:
            self.live.set_carved_by_view(views, res.occupancy, res.grid)
            self._carved_for = res
        step = self._bounded(self.carve_step, -1, max(len(self.app.cameras) - 1, 0), integer=True)
        n = self.live.show_carve_step(None if step < 0 else step)
        which = "all views" if step < 0 else f"view {self.app.view_ids[step]}"
        total = int((views >= 0).sum())
        mine = total if step < 0 else int((views == step).sum())
        self.carve_info.content = f"{which}: carves {mine:,} of {views.size:,} voxels ({n:,} shown near the hull)"
        if step >= 0:
            self.view.value = step

    # ------------------------------------------------------------ roi
    def _view_index(self):
        return self._bounded(self.view, 0, max(len(self.app.cameras) - 1, 0), integer=True)

    def roi(self):
        size = self._roi_size()
        c = np.asarray(self._roi_centre, float)
        return c - size / 2, c + size / 2

    def _update_roi_info(self):
        lo, hi = self.roi()
        vs = self._bounded(self.voxel, *VOXEL_RANGE)
        n, b = _scene.roi_stats(lo, hi, vs, self._bounded(self.tolerance, 0, self._max_tolerance, integer=True))
        self.roi_info.content = (
            f"{n:,} voxels at {vs:g} mm, about {_scene.human_bytes(b)}  \n"
            f"min {np.round(lo, 1).tolist()} max {np.round(hi, 1).tolist()} mm"
        )

    def _roi_gizmo_toggle(self, on):
        sc = self.live.server.scene
        if not on:
            for h in (self._roi_box, self._roi_gizmo):
                if h is not None:
                    h.remove()
            self._roi_box = self._roi_gizmo = None
            return
        size = float(np.linalg.norm(self._roi_size()))
        self._roi_gizmo = sc.add_transform_controls(
            "/roi", scale=0.35 * size, disable_rotations=True, position=tuple(self._roi_centre),
            translation_limits=tuple((-5 * size, 5 * size) for _ in range(3)),
        )
        self._update_roi_box()

        limit = 5 * size  # the gizmo's translation limits, enforced here too: a client may send any position

        @self._roi_gizmo.on_update
        def _(_e):
            pos = np.asarray(self._roi_gizmo.position, float)
            if pos.shape == (3,) and np.all(np.isfinite(pos)):
                self._roi_centre = np.clip(pos, -limit, limit)
            self._update_roi_info()

    def _update_roi_box(self):
        self._update_roi_info()
        if self._roi_gizmo is None:
            return
        self._roi_box = self.live.server.scene.add_box(
            "/roi/box", color=(255, 150, 0), dimensions=tuple(float(v) for v in self._roi_size()), wireframe=True,
        )
