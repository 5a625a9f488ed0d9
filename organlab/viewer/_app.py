"""The session viewer: a session's views, its reconstruction, re-run live.

:class:`SessionViewer` loads a session, shows it in a :class:`LiveView`, and
recomputes in a worker thread whenever a control changes, streaming each
stage's result (voxels first, then the mesh, measurements and agreement).  It
only calls stage functions (silhouette, carving, coloring, surface).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from ._live import LiveView
from ._worker import LatestWorker


@dataclasses.dataclass(frozen=True)
class Settings:
    """What a re-run depends on (the GUI's controls).

    threshold : float or None -- for every view, grey levels (subtraction) or Delta E (a backdrop session's
        keying); None = automatic per view
    voxel_size : float, mm
    method : {'hull', 'coloring', 'space_carving'}
    hull : {'subvoxel', 'thesis'}
    color_threshold : float or None -- None = colouring's automatic threshold
    tolerance : int
    roi : ((3,), (3,)) tuple of float, mm
    """

    threshold: float | None = None
    voxel_size: float = 1.0
    method: str = "hull"
    hull: str = "subvoxel"
    color_threshold: float | None = None
    tolerance: int = 0
    roi: tuple = ((-70.0, -70.0, 0.0), (70.0, 70.0, 200.0))


@dataclasses.dataclass
class Result:
    """The newest finished reconstruction shown."""

    settings: Settings
    grid: object
    occupancy: np.ndarray
    mesh: object
    masks: list
    colors: np.ndarray | None = None
    agreement: np.ndarray | None = None
    n_surface_voxels: int = 0
    seconds: float = 0.0
    generation: int = 0
    views: np.ndarray | None = None  # carving_views, computed on demand
    timings: dict = dataclasses.field(default_factory=dict)  # seconds per stage
    raw_mesh: object = None  # the marching-cubes mesh before organlab.surface.finish_surface
    aaa: object = None  # organlab.surface.AAAMeasures (AAA sessions)
    aaa_error: str | None = None  # why an AAA session was not measured
    color_threshold: float | None = None  # the colour threshold colouring used (its automatic one unless set)


def _load_cameras(session):
    """Cameras of a session: given, its matching calibration.json, or calibrated now (nothing written)."""
    from ..pipeline import session_cameras

    return session_cameras(session)


class SessionViewer:
    """A live viewer of one session (``organlab view``).

    Parameters
    ----------
    session : Session or str or Path
    result : str or Path, optional
        A folder written by ``organlab reconstruct`` (``voxels.npz``,
        ``mesh.ply``, ``report.json``) shown instead of reconstructing at start.
    voxel_size : float, mm
        Voxel size of the first reconstruction.
    views : sequence of int, optional
        Use only these views (e.g. every third one, for a quick look).
    host, port : as :class:`LiveView`
    stream : bool
        Carve view by view at start, updating the scene after each view.

    Attributes
    ----------
    live : LiveView
    result : Result or None
    worker : LatestWorker
    """

    def __init__(self, session, *, result=None, voxel_size=1.0, views=None, host="127.0.0.1", port=8080,
                 stream=True, verbose=False):
        from ..session import Session, load_session

        self.session = session if isinstance(session, Session) else load_session(session)
        s = self.session
        if not s.views:
            from ..errors import SessionError

            raise SessionError(f"{s.json_path}: views: the session has no views to show")
        cams = _load_cameras(s)
        keep = list(range(len(s.views))) if views is None else [int(i) for i in views]
        self.view_ids = keep
        self.cameras = [cams[i] for i in keep]
        self.images = [s.read(s.views[i].image, key=f"views[{i}].image") for i in keep]
        self._prepare_silhouettes()
        roi = (tuple(map(float, s.roi_min)), tuple(map(float, s.roi_max)))
        self.settings = Settings(voxel_size=float(voxel_size), roi=roi)
        self.result = None
        self.status = "starting"
        self.errors = []
        from ..surface import is_aaa_session

        self.is_aaa = is_aaa_session(s)  # AAA measures after each re-run, as organlab reconstruct
        # pymeshlab (finish_surface, in the worker thread) must be imported first in this thread:
        # imported first in the worker, the process aborted at exit (glibc malloc_consolidate)
        import pymeshlab  # noqa: F401
        self.live = LiveView(roi=roi, host=host, port=port, verbose=verbose, label=f"organlab: {s.name}")
        from concurrent.futures import ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(2, thread_name_prefix="organlab-viewer-silhouettes")
        self.worker = LatestWorker(self._job, on_error=self._error)
        from ._gui import Controls

        self.controls = Controls(self)
        if result is not None:
            self._show_result_folder(Path(result))
        else:
            self.worker.submit(("stream" if stream else "run", self.settings))

    # ------------------------------------------------------------ silhouettes
    def _prepare_silhouettes(self):
        """What does not depend on the threshold, once: organlab.silhouette.SilhouetteModel of the shown views
        (background subtraction, or keying for a session with a ``backdrop``, as organlab reconstruct)."""
        from ..silhouette import SilhouetteModel

        self._model = SilhouetteModel.from_session(self.session, images=self.images, views=self.view_ids)
        self.threshold_units = self._model.units
        self.auto_thresholds = self._model.auto_thresholds()
        autos = [t for t in self.auto_thresholds if t is not None]
        self.auto_threshold = float(np.median(autos)) if autos else None
        self._sil_cache = {}

    def silhouette(self, j, threshold=None):
        """Mask and coverage of view ``j`` at a threshold (None: its automatic one).

        Returns
        -------
        mask : (H, W) bool
        coverage : (H, W) float32
        """
        t = self.auto_thresholds[j] if threshold is None else float(threshold)
        key = (j, None if t is None else round(t, 4))
        hit = self._sil_cache.get(key)
        if hit is None:
            sil = self._model.silhouette(j, threshold=t)
            hit = (sil.mask, sil.coverage)
            if len(self._sil_cache) > 4 * len(self.view_ids):
                self._sil_cache.clear()
            self._sil_cache[key] = hit
        return hit

    # ------------------------------------------------------------ jobs
    def rerun(self, **changes):
        """Re-run with changed settings (any field of :class:`Settings`); returns the generation."""
        self.settings = dataclasses.replace(self.settings, **changes)
        return self.worker.submit(("run", self.settings))

    def wait(self, generation=None, timeout=120.0):
        """Wait until a re-run (default: the newest) is shown."""
        return self.worker.wait(generation, timeout)

    def _error(self, exc, tb):
        self.errors.append(tb)
        self.status = f"error: {exc}"
        self.controls.show_status(self.status)

    def _job(self, gen, request, check):
        kind, st = request
        t0 = time.perf_counter()
        from .. import carving
        from ..grid import VoxelGrid

        grid = VoxelGrid.from_roi(st.roi[0], st.roi[1], st.voxel_size)
        self.status = f"run {gen}: silhouettes"
        self.controls.show_status(self.status)
        tm = {}
        masks, covs = [], []
        # OpenCV releases the GIL: re-threshold the views on two threads
        for m, c in self._pool.map(lambda j: self.silhouette(j, st.threshold), range(len(self.cameras))):
            masks.append(m)
            covs.append(c)
        check()
        tm["silhouettes"] = time.perf_counter() - t0
        if kind == "stream":
            self._stream(grid, st, masks, check)
        self.status = f"run {gen}: carving"
        t1 = time.perf_counter()
        if st.hull == "thesis":
            occ = carving.carve(masks, self.cameras, grid, tolerance=st.tolerance)
            field = None
        else:
            field = carving.hull_field(covs, self.cameras, grid, tolerance=st.tolerance, progress=lambda d, n: check(),
                                       sparse=True)  # in a narrow band: cost grows with the surface
            occ = field.occupancy()
        check()
        if not occ.any():
            raise ValueError("carving left no voxel: lower the threshold, raise the tolerance or widen the roi")
        tm["carving"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        shown = self.controls.show_voxels or "mesh" not in self.live._handles
        n_surf = self.live.set_voxels(occ, grid, visible=shown)
        colors = colored = color_t = None
        if st.method != "hull":
            occ, colors, colored, color_t = self._color(occ, grid, masks, st, check)
            field = None
            n_surf = self.live.set_voxels(occ, grid, colors, visible=shown)
        tm["voxels sent"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        raw = self._mesh(occ, field, colors, colored, grid)
        tm["mesh"] = time.perf_counter() - t1
        check()
        self.live.set_mesh(raw, visible=self.controls.show_mesh)
        self.live.set_visible("voxels", self.controls.show_voxels)
        tm["scene updated"] = time.perf_counter() - t0  # voxels and marching-cubes mesh queued for the browser
        mesh, aaa, aaa_error = self._finish_and_measure(raw, occ if (colors is not None or field is None) else field,
                                                        grid, check, tm)
        res = Result(st, grid, occ, mesh, masks, colors, None, n_surf, 0.0, gen, raw_mesh=raw, aaa=aaa,
                     aaa_error=aaa_error, color_threshold=color_t)
        t1 = time.perf_counter()
        res.agreement = self._agreement(mesh, masks)
        tm["agreement"] = time.perf_counter() - t1
        res.seconds = time.perf_counter() - t0
        res.timings = tm
        check()
        self.result = res
        self.status = f"run {gen}: done in {res.seconds:.2f} s"
        self.controls.show_result(res)

    def _stream(self, grid, st, masks, check):
        """Carve view by view, showing each view and the hull so far (start-up)."""
        from ..carving import ProgressiveCarver

        carver = ProgressiveCarver(grid, tolerance=st.tolerance)
        last = 0.0
        for j, (img, cam, m) in enumerate(zip(self.images, self.cameras, masks)):
            if j >= len(self.live.cameras):
                self.live.add_view(img, cam, m)
            occ = carver.add_view(m, cam)
            now = time.perf_counter()
            if now - last > 0.1 or j == len(masks) - 1:  # at most ~10 updates/s
                self.live.set_voxels(occ, grid)
                last = now
            self.status = f"streaming: view {j + 1}/{len(masks)}"
            self.controls.show_status(self.status)
            check()
        self.controls.views_added()

    def _color(self, occ, grid, masks, st, check):
        from .. import coloring

        # as organlab.pipeline colours: automatic threshold unless one is set, exposure, shading measure, guard
        kind = "voxel_coloring" if st.method == "coloring" else "space_carving"
        res = coloring.color_voxels(self.images, self.cameras, occ, grid, method=kind, masks=masks,
                                    progress=lambda d, n: check(), **coloring.PIPELINE_OPTIONS,
                                    threshold="auto" if st.color_threshold is None else st.color_threshold)
        return res.occupancy, res.colors, res.colored, float(res.threshold)

    @staticmethod
    def _mesh(occ, field, colors, colored, grid):
        from ..surface import color_vertices, mesh_from_field

        # after colouring, the surface is the coloured voxel model's (as organlab.pipeline does)
        mesh = mesh_from_field(field if field is not None else occ, grid)
        if colors is not None:
            mesh = color_vertices(mesh, colors, colored, grid)
        return mesh

    def _finish_and_measure(self, raw, volume, grid, check, tm):
        """The stages after marching cubes, as organlab.pipeline runs them: the finished
        surface (:func:`organlab.surface.finish_surface`) and, for an AAA session, the
        measures (:func:`organlab.surface.measure_aaa` of the volume the mesh came from).

        Returns the finished mesh (shown), the measures (shown) or None, and why an AAA
        session was not measured (or None).
        """
        from ..errors import OrganlabError
        from ..pipeline import pixel_footprint
        from ..surface import finish_surface, measure_aaa

        t1 = time.perf_counter()
        mesh, _ = finish_surface(raw, voxel_size=grid.voxel_size, min_edge_mm=pixel_footprint(self.cameras, grid))
        tm["finish"] = time.perf_counter() - t1
        check()
        aaa = error = None
        if self.is_aaa:
            t1 = time.perf_counter()
            try:
                aaa = measure_aaa(volume, grid)
            except OrganlabError as e:  # noted in the read-out, as the pipeline notes it in the report
                error = str(e)
            tm["aaa"] = time.perf_counter() - t1
            check()
        self._show_surface(mesh, aaa)
        return mesh, aaa, error

    def _show_surface(self, mesh, aaa):
        """The finished mesh (translucent when the AAA measures inside it are shown) and the measures."""
        shown = aaa is not None and self.controls.show_aaa
        self.live.set_mesh(mesh, visible=self.controls.show_mesh, opacity=0.5 if shown else None)
        self.live.set_aaa(aaa, visible=self.controls.show_aaa)

    def _agreement(self, mesh, masks):
        """IoU of the mesh's projection with each view's silhouette, (n_views,) float64 (organlab.agreement)."""
        from ..agreement import view_agreement

        agr = view_agreement(mesh, self.cameras, masks, voxel_size=self.settings.voxel_size)
        return np.array([v["iou"] for v in agr.views], dtype=np.float64)

    def carving_views(self):
        """Carve-by-view of the shown result (computed once per result), grid.shape int16."""
        from ..carving import carving_views

        res = self.result
        if res is None:
            return None
        if res.views is None:
            res.views = carving_views(res.masks, self.cameras, res.grid)
        return res.views

    def hull_in_view(self, j):
        """The shown mesh projected into view ``j``, (H, W) bool, or None."""
        from ..agreement import model_mask

        if self.result is None:
            return None
        cam = self.cameras[j]
        return model_mask(self.result.mesh, cam, (cam.height, cam.width))

    # ------------------------------------------------------------ --result
    def _show_result_folder(self, folder):
        from ..errors import SessionError
        from ..grid import VoxelGrid
        from ..surface import read_ply

        vox, ply, rep = folder / "voxels.npz", folder / "mesh.ply", folder / "report.json"
        for p in (vox, ply):
            if not p.is_file():
                raise SessionError(f"{p}: missing; run 'organlab reconstruct {self.session.root} --out {folder}' first")
        with np.load(vox, allow_pickle=False) as z:
            occ = z["occupancy"].astype(bool)
            origin, vs = z["origin_mm"], float(z["voxel_size_mm"])
            colors = z["colors"] if "colors" in z.files else None
        grid = VoxelGrid(tuple(origin), vs, occ.shape)
        mesh = read_ply(ply)
        report = json.loads(rep.read_text()) if rep.is_file() else {}
        thresholds = [v.get("silhouette_threshold") for v in report.get("views", [])]
        masks = []
        for j, (img, cam) in enumerate(zip(self.images, self.cameras)):
            i = self.view_ids[j]
            t = thresholds[i] if i < len(thresholds) else None
            m, _ = self.silhouette(j, t)
            masks.append(m)
            self.live.add_view(img, cam, m)
        self.controls.views_added()
        lo, hi = grid.bounds
        st = dataclasses.replace(self.settings, voxel_size=vs, method=report.get("method", "hull"),
                                 hull=report.get("hull", "subvoxel"), roi=(tuple(lo), tuple(hi)))
        self.settings = st
        n = self.live.set_voxels(occ, grid, colors)
        aaa, aaa_error = self._result_aaa(folder, report)
        self._show_surface(mesh, aaa)
        self.live.set_visible("voxels", self.controls.show_voxels)
        res = Result(st, grid, occ, mesh, masks, colors, self._agreement(mesh, masks), n, 0.0, 0, aaa=aaa,
                     aaa_error=aaa_error)
        self.result = res
        self.status = f"result loaded from {folder}"
        self.controls.show_result(res)

    def _result_aaa(self, folder, report):
        """The AAA measures of a result folder whose report has them (or of an AAA session):
        the report keeps only their summary, so they are measured again from ``voxels.npz``
        (the same volume and function as ``organlab reconstruct``)."""
        from ..errors import OrganlabError
        from ..surface import load_voxels, measure_aaa

        if "aaa" not in report and not self.is_aaa:
            return None, None
        try:
            return measure_aaa(*load_voxels(folder)), None
        except OrganlabError as e:
            return None, str(e)

    # ------------------------------------------------------------ lifetime
    @property
    def url(self):
        return self.live.url

    def iframe(self, **kw):
        """The viewer embedded in a notebook cell (``IPython.display.IFrame``)."""
        return self.live.iframe(**kw)

    def _repr_html_(self):
        return self.live._repr_html_()

    def stop(self):
        """Stop the worker and the server (frees the port)."""
        self.worker.stop()
        self._pool.shutdown(wait=True)
        self.live.stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
