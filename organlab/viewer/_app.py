"""The session viewer: a session's views, its reconstruction, re-run live.

:class:`SessionViewer` loads a session, shows it in a :class:`LiveView`, and
re-runs its :class:`organlab.engine.Engine` in a worker thread whenever a
control changes, streaming each stage's result as the engine reports it
(voxels first, then the mesh, the measures and the agreement).  The engine is
kept across slider moves, so a new threshold re-runs the silhouettes onward
and a new voxel size keeps the silhouettes; a newer request cancels the
running one.  No stage runs here: this is a face.
"""

from __future__ import annotations

import collections
import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..agreement import model_mask
from ..calibration import needs_calibration
from ..engine import AgreementFigures, Engine, Reconstruction, Settings
from .. import validate
from ..errors import OrganlabError, SessionError
from ..nbcam import CompileWatch
from ..session import Session, load_session
from ._frustums import PoseFrustums
from ._gui import Controls
from ._live import LiveView
from ._worker import LatestWorker

__all__ = ["SessionViewer", "Settings", "Result"]


def check_result_folder(folder: str | Path, session: Session) -> Path:
    """A folder written by ``organlab reconstruct`` from ``session``, checked before anything starts.

    Raises
    ------
    SessionError
        One line: the folder is missing, is a file, lacks ``voxels.npz`` or
        ``mesh.ply``, or its ``report.json`` names another session or other
        view images.
    """
    folder = Path(folder)
    fix = f"give a folder written by 'organlab reconstruct {session.root} --out DIR'"
    if not folder.exists():
        raise SessionError(f"{folder}: result folder does not exist; {fix}")
    if not folder.is_dir():
        raise SessionError(f"{folder}: is a file, not a result folder; {fix}")
    for name in ("voxels.npz", "mesh.ply"):
        if not (folder / name).is_file():
            raise SessionError(f"{folder / name}: missing, so {folder} is not a result folder; {fix}")
    rep = folder / "report.json"
    report = validate.read_json(rep, error=SessionError, fix=fix) if rep.is_file() else {}
    if isinstance(report, dict):  # another session's result first: the likelier mistake than a damaged file
        views = report.get("views") if isinstance(report.get("views"), list) else []
        images = [v.get("image") for v in views if isinstance(v, dict)]
        mine = [session.relpath(v.image) for v in session.views]
        name = report.get("session")
        if (name is not None and name != session.name) or (images and images != mine):
            raise SessionError(
                f"{folder}: made from session '{validate.printable(name)}' ({len(images)} views), not from "
                f"{session.root} ('{validate.printable(session.name)}', {len(mine)} views); view it with its own "
                f"session, or {fix}")
    try:  # every file read through its type, checked: one line for a damaged one, before the server starts
        Reconstruction.load(folder, session=session)
    except SessionError:
        raise
    except OrganlabError as e:
        raise SessionError(str(e)) from None
    return folder


@dataclasses.dataclass
class Result:
    """The newest finished reconstruction shown: the engine's :class:`Reconstruction` and how it was shown.

    Attributes
    ----------
    reconstruction : Reconstruction
    generation : int
        The request it answered.
    seconds : float
        Request to last read-out, s.
    timings : dict of str -> float
        Seconds per step of the job (the stages run, the scene updates).
    n_surface_voxels : int
        Voxels shown.
    views : (nx, ny, nz) int16 or None
        :meth:`Engine.carving_views`, computed on demand.
    """

    reconstruction: Reconstruction
    generation: int = 0
    seconds: float = 0.0
    timings: dict = dataclasses.field(default_factory=dict)
    n_surface_voxels: int = 0
    views: np.ndarray | None = None

    @property
    def settings(self) -> Settings:
        return self.reconstruction.settings

    @property
    def grid(self):
        return self.reconstruction.grid

    @property
    def occupancy(self) -> np.ndarray:
        return self.reconstruction.occupancy

    @property
    def mesh(self):
        return self.reconstruction.mesh

    @property
    def raw_mesh(self):
        return self.reconstruction.raw_mesh

    @property
    def masks(self) -> list:
        return self.reconstruction.masks

    @property
    def colors(self) -> np.ndarray | None:
        return self.reconstruction.colors

    @property
    def aaa(self):
        return self.reconstruction.aaa

    @property
    def aaa_error(self) -> str | None:
        return self.reconstruction.aaa_error

    @property
    def color_threshold(self) -> float | None:
        return self.reconstruction.color_threshold

    @property
    def report(self) -> dict:
        """The run's report (as report.json): its ``warnings`` are shown in the panel."""
        return self.reconstruction.report or {}

    @property
    def figures(self) -> AgreementFigures | None:
        """The agreement figures, as report.json and the CLI summary give them."""
        return self.reconstruction.agreement

    @property
    def agreement(self) -> np.ndarray | None:
        """IoU of the model's projection with each shown view's silhouette, (n_views,) float64."""
        f = self.figures
        return None if f is None else np.asarray(f.iou, dtype=np.float64)


#: The engine's stage results of this many recent settings are kept (:meth:`organlab.engine.Engine.kept`):
#: going back to one (the slider back to a value, *Automatic threshold* ticked again) runs no stage.
RECENT = 3
#: ... for grids up to this many voxels (0.75 mm on the sample's roi); above, one result's arrays are big.
RECENT_MAX_VOXELS = 16_000_000


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
    host, port, token : as :class:`LiveView` (a non-loopback host requires a token)
    stream : bool
        Carve view by view at start, updating the scene after each view.

    Attributes
    ----------
    engine : Engine
        Runs the stages; kept across re-runs.
    live : LiveView
    result : Result or None
    worker : LatestWorker
    """

    def __init__(self, session: Session | str | Path, *, result: str | Path | None = None, voxel_size: float = 1.0,
                 views: Any = None, host: str = "127.0.0.1", port: int = 8080, stream: bool = True,
                 verbose: bool = False, say: Any = None, token: str | None = None):
        say = say or (lambda _line: None)
        self._say = say
        self.session = session if isinstance(session, Session) else load_session(session)
        s = self.session
        if not s.views:
            raise SessionError(f"{s.json_path}: views: the session has no views to show")
        folder = None if result is None else check_result_folder(result, s)  # before the server starts
        self.engine = Engine(s, views=views)
        self.view_ids = self.engine.views
        roi = self.engine.roi(Settings())
        self.settings = Settings(voxel_size=float(voxel_size), roi=roi).validate()
        self.result = None
        self._recent = collections.OrderedDict()  # engine.key('checks', settings) -> engine.kept('checks')
        self.status = "starting"
        self.errors = []
        self._runs = 0  # re-runs shown; the one running is "run {self._runs + 1}"
        # the server first: its address is printed (say) and the page shows the start-up steps
        self.live = LiveView(roi=roi, host=host, port=port, verbose=verbose, label=f"organlab: {s.name}", token=token)
        say(f"organlab view: {s.name} at {self.url}  (Ctrl-C stops)")
        notice = self.live.server.gui.add_markdown("*starting*")
        self._notice = notice
        self._label = "starting"
        # numba compiling a kernel (not in its on-disk cache: the first run after installing, unless
        # `make warm` ran) is said, in the terminal and the page: it took 20-50 s of silence before
        self.compiling = CompileWatch(self._compiling).start()

        def step(text):
            self.status = f"starting: {text}"
            if hasattr(self, "controls"):
                self.controls.show_status(self.status)
            else:
                notice.content = f"*{self.status}*"
            say(f"  {self.status}")

        n = len(self.view_ids)
        step(f"reading {n} view{'s' if n != 1 else ''}")
        self.images = self.engine.images
        step("cameras " + ("(the session's calibration.json, or calibrating from its board images)"
                           if needs_calibration(s) else "(given in session.json)"))
        self.cameras = self.engine.cameras()
        step("background and silhouette model")
        model = self.engine.silhouette_model  # background (or backdrop keying), once: a threshold only re-thresholds
        self.threshold_units = model.units
        self.auto_thresholds = model.auto_thresholds()
        autos = [t for t in self.auto_thresholds if t is not None]
        self.auto_threshold = float(np.median(autos)) if autos else None
        self.is_aaa = self.engine.is_aaa  # AAA measures after each re-run, as organlab reconstruct
        notice.remove()
        self._notice = None
        # pymeshlab (finish_surface, in the worker thread) must be imported first in this thread:
        # imported first in the worker, the process aborted at exit (glibc malloc_consolidate).  After the
        # silhouette model: numba's parallel kernels must choose their threads before pymeshlab's old libtbb loads
        import pymeshlab  # noqa: F401
        self.worker = LatestWorker(self._job, on_error=self._error)
        self.controls = Controls(self)
        self.pose_frustums = PoseFrustums(self.live)  # the cameras before and after the poses stage
        if folder is not None:
            step(f"reading {folder}")
            self._show_result_folder(folder)
        else:
            self.status = "start-up: reconstructing"
            self.controls.show_status(self.status)
            self.worker.submit(("stream" if stream else "run", self.settings))

    # ------------------------------------------------------------ jobs
    def rerun(self, **changes: Any) -> int:
        """Re-run with changed settings (any field of :class:`Settings`); returns the generation."""
        self.settings = self.settings.replace(**changes)
        return self.worker.submit(("run", self.settings))

    def wait(self, generation: int | None = None, timeout: float = 120.0) -> bool:
        """Wait until a re-run (default: the newest) is shown."""
        return self.worker.wait(generation, timeout)

    def _compiling(self, name):
        """A numba kernel compiles (CompileWatch, in the compiling thread): said once, shown in the status."""
        if self.compiling.count == 1:
            self._say(f"  compiling: organlab's numba kernels compile on their first run after installing, once "
                      f"(`make warm` does it at install); first: {name}")
        self.status = f"{self._label}: compiling numba kernels (the first run after installing; once)"
        if getattr(self, "controls", None) is not None:
            self.controls.show_status(self.status)
        elif self._notice is not None:
            self._notice.content = f"*{self.status}*"

    def _error(self, exc, tb):
        self.errors.append(tb)
        self.status = f"error: {exc}"
        self.controls.show_status(self.status)

    def _job(self, gen, request, check):
        kind, st = request
        # the first reconstruction is the start-up's; re-runs are numbered from the first change, counting the
        # runs shown (a request superseded by a newer one, as a dragged slider sends, takes no number)
        label = "start-up" if gen == 1 and kind == "stream" else f"run {self._runs + 1}"
        self._label = label
        compiled0 = self.compiling.seconds
        t0 = time.perf_counter()
        tm = {}
        last = [t0]

        def cancel():
            return self.worker.stale(gen)

        def lap(name):
            now = time.perf_counter()
            tm[name] = now - last[0]
            last[0] = now

        if kind == "stream":
            self._stream(st, cancel)
            lap("stream")
        shown = {"n": 0}

        def voxels_first():
            """Whether the voxels are shown as soon as carved: when displayed, or nothing else is shown yet."""
            return self.controls.show_voxels or "mesh" not in self.live._handles

        def on_stage(name, result):
            if name == "calibration" or (name == "coloring" and result is None):  # kept / no colouring
                return
            lap(name)
            if cancel():  # superseded by a newer request: nothing of it is sent (the engine stops at its next check)
                return
            if name == "silhouettes":
                self.status = f"{label}: carving"
            elif name == "carving":  # voxels first, when they are displayed
                # hidden voxels (Display > Model: mesh) are sent after the full update: making them reads the
                # occupancy, which the engine otherwise makes after the surface, and they would wait for it
                if voxels_first():
                    shown["n"] = self.live.set_voxels(result.occupancy, result.grid, visible=True)
                    shown["voxels"] = True
                    lap("voxels sent")
                self.status = f"{label}: surface"
            elif name == "coloring" and result is not None:
                if voxels_first():
                    shown["n"] = self.live.set_voxels(result.occupancy, self.engine.grid(st), result.colors,
                                                      visible=True)
                    shown["voxels"] = True
                    lap("voxels sent")
            elif name == "mesh":  # marching cubes: shown before it is finished
                self.live.set_mesh(result, visible=self.controls.show_mesh)
                self.live.set_visible("voxels", self.controls.show_voxels)
                tm["scene updated"] = time.perf_counter() - t0  # voxels and marching-cubes mesh queued
            elif name == "surface":
                self._show_surface(result.mesh, result.aaa)
                tm["surface shown"] = time.perf_counter() - t0  # the finished surface and AAA measures queued
                self.status = f"{label}: agreement"
            self.controls.show_status(self.status)

        self.status = f"{label}: silhouettes"
        self.controls.show_status(self.status)
        recent = self._recent.get(self.engine.key("checks", st))
        if recent is not None:  # shown a few requests ago: the engine takes its stages back and re-runs none
            self.engine.keep(recent)
        rec = self.engine.run(st, on_stage=on_stage, cancel=cancel)
        check()  # a newer request arrived meanwhile: not shown
        self._remember(st, rec)
        if not shown.get("voxels"):  # hidden while the surface was made: sent now, for the display's switch
            shown["n"] = self.live.set_voxels(rec.occupancy, rec.grid, rec.colors, visible=self.controls.show_voxels)
            lap("voxels sent")
        res = Result(rec, gen, time.perf_counter() - t0, tm, shown["n"])
        self.result = res
        if label != "start-up":
            self._runs += 1
        compiled = self.compiling.seconds - compiled0
        self.status = f"{label}: done in {res.seconds:.2f} s" + (
            f" ({compiled:.1f} s of it compiling numba kernels, once)" if compiled >= 0.05 else "")
        self.controls.show_result(res)
        self.pose_frustums.show(self.cameras, rec.cameras, (rec.report or {}).get("poses"))

    def _remember(self, st, rec):
        """Keep the engine's stages of the result shown (the :data:`RECENT` newest settings)."""
        if rec.grid is None or rec.grid.n_voxels > RECENT_MAX_VOXELS:
            return
        key = self.engine.key("checks", st)
        self._recent[key] = self.engine.kept("checks")
        self._recent.move_to_end(key)
        while len(self._recent) > RECENT:
            self._recent.popitem(last=False)

    def _stream(self, st, cancel):
        """Carve view by view, showing each view and the hull so far (start-up)."""
        last = [0.0]
        n = len(self.view_ids)

        def on_view(j, sil, cam, occ, grid):
            if j >= len(self.live.cameras):
                self.live.add_view(self.images[j], cam, sil.mask)
            now = time.perf_counter()
            if now - last[0] > 0.1 or j == n - 1:  # at most ~10 updates/s
                self.live.set_voxels(occ, grid)
                last[0] = now
            self.status = f"streaming: view {j + 1}/{n}"
            self.controls.show_status(self.status)

        self.engine.stream_hull(st, on_view, cancel=cancel)
        self.controls.views_added()

    def _show_surface(self, mesh, aaa):
        """The finished mesh (translucent when the AAA measures inside it are shown) and the measures."""
        shown = aaa is not None and self.controls.show_aaa
        self.live.set_mesh(mesh, visible=self.controls.show_mesh, opacity=0.5 if shown else None)
        self.live.set_aaa(aaa, visible=self.controls.show_aaa)

    def carving_views(self) -> np.ndarray | None:
        """Carve-by-view of the shown result (computed once per result), grid.shape int16."""
        res = self.result
        if res is None:
            return None
        if res.views is None:
            res.views = self.engine.carving_views(res.reconstruction)
        return res.views

    def hull_in_view(self, j: int) -> np.ndarray | None:
        """The shown mesh projected into view ``j``, (H, W) bool, or None."""
        if self.result is None:
            return None
        cam = self.cameras[j]
        return model_mask(self.result.mesh, cam, (cam.height, cam.width))

    # ------------------------------------------------------------ --result
    def _show_result_folder(self, folder):
        rec = self.engine.load_result(folder)
        rec.report.setdefault("warnings", [])
        for j, (img, cam, m) in enumerate(zip(self.images, self.cameras, rec.masks)):
            self.live.add_view(img, cam, m)
        self.controls.views_added()
        self.settings = rec.settings
        n = self.live.set_voxels(rec.occupancy, rec.grid, rec.colors)
        self._show_surface(rec.mesh, rec.aaa)
        self.live.set_visible("voxels", self.controls.show_voxels)
        res = Result(rec, 0, 0.0, {}, n)
        self.result = res
        self.status = f"result loaded from {folder}"
        self.controls.show_result(res)

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
        self.compiling.stop()
        self.live.stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
