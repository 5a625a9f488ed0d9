"""The one engine that runs the stages: a session and typed settings in, a reconstruction out.

Every face calls it: :func:`organlab.pipeline.reconstruct` (the CLI and the
notebooks), the live viewer (:class:`organlab.viewer.SessionViewer`), the
carving tuner widget and batch sweeps.  The stage sequence exists here once::

    calibration -> silhouettes -> carving -> coloring -> surface -> checks

An :class:`Engine` keeps the result of every stage with the settings it was
computed from, and a new :meth:`Engine.run` re-runs a stage only when a
setting it depends on (:data:`DEPENDS`), or an earlier stage, changed: a new
threshold re-runs the silhouettes and what follows, never the calibration; a
new voxel size keeps the calibration and the silhouettes.

Examples
--------
>>> from organlab.engine import Engine, Settings
>>> eng = Engine("sample_sessions/aaa_phantom", views=range(0, 36, 6))
>>> rec = eng.run(Settings(voxel_size=4.0, finish=False), until="carving")
>>> bool(rec.occupancy.any()), rec.mesh is None
(True, True)
>>> eng.run(Settings(voxel_size=4.0, finish=False, threshold=20.0), until="carving").report is None
True
>>> eng.computed["calibration"], eng.computed["silhouettes"]   # runs of each stage so far
(1, 2)
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from . import __version__, surface, validate
from .checks import model_warnings, roi_faces_touched
from .agreement import (MANY_FLAGGED, ViewAgreement, hull_masks, suggest_angles, suggestion_text, view_agreement,
                        worst_views)
from .calibration import calibration_for
from .carving import BandField, ProgressiveCarver, carve, carving_views, hull_field
from .errors import CalibrationError, OrganlabError, SessionError, SettingsError
from .grid import VoxelGrid
from .lazy import later
from .preflight import atomic_output_dir, available_memory, check_grid_memory, check_image_memory
from .poses import MODES as POSE_MODES, refine_poses
from .progress import NullProgress
from .session import Session, load_session, write_json
from .silhouette import Silhouette, SilhouetteModel, silhouette
from .surface import (color_vertices, finish_surface, is_aaa_session, measure, measure_aaa, mesh_from_field,
                      read_ply, release_heap)

# The colouring (method != 'hull'): imported on its first use, so that the default run (the hull) does not load its
# modules and kernels (0.1 s CPU of the command's imports, issue 24)
DEFAULT_PHOTO_THRESHOLD = later("organlab.coloring", "DEFAULT_PHOTO_THRESHOLD")
PIPELINE_OPTIONS = later("organlab.coloring", "PIPELINE_OPTIONS")
color_voxels = later("organlab.coloring", "color_voxels")
photo_carve = later("organlab.coloring", "photo_carve")
report_entry = later("organlab.coloring", "report_entry")

__all__ = ["Settings", "SettingsError", "STAGES", "DEPENDS", "METHODS", "HULL_METHODS", "Cancelled", "Engine",
           "Reconstruction", "AgreementFigures", "CalibrationStage", "CarvingStage", "ColoringStage", "SurfaceStage",
           "ChecksStage", "LiveHull", "run", "pixel_footprint", "ColorThresholdRange", "color_threshold_range"]

METHODS = ("hull", "coloring", "space_carving", "photo")
HULL_METHODS = ("subvoxel", "thesis")
#: Settings.joint_silhouettes: "auto" (the default) runs the joint step for a keyed (backdrop) session with >= 8 views.
JOINT_MODES = ("auto", "on", "off")


class ColorThresholdRange(NamedTuple):
    """What a face offers for ``Settings.color_threshold`` under one method (a slider's bounds, step, unit).

    ``default`` is the value "automatic" stands for when it is fixed (``'photo'``'s NCC gain), None when
    the colouring measures it per run (``'coloring'``, ``'space_carving'``).
    """

    low: float
    high: float
    step: float
    unit: str
    default: float | None


def color_threshold_range(method: str) -> ColorThresholdRange:
    """The useful range of ``Settings.color_threshold`` for a colouring ``method``.

    ``'coloring'`` and ``'space_carving'`` take a standard deviation in grey
    levels (1-60); ``'photo'`` takes an NCC gain (0.05-1, default
    :data:`organlab.coloring.DEFAULT_PHOTO_THRESHOLD`: 0.5x-2x of it lies well
    inside).  ``'hull'`` has no colour threshold: SettingsError.

    Examples
    --------
    >>> color_threshold_range("photo").default, color_threshold_range("coloring").unit
    (0.25, 'grey levels')
    """
    if method == "photo":
        return ColorThresholdRange(0.05, 1.0, 0.01, "NCC gain", float(DEFAULT_PHOTO_THRESHOLD.resolve()))
    if method in ("coloring", "space_carving"):
        return ColorThresholdRange(1.0, 60.0, 0.5, "grey levels", None)
    raise SettingsError("method", f"has no colour threshold unless one of {METHODS[1:]}, got {method!r}")


class Cancelled(Exception):
    """Raised by :meth:`Engine.run` when its ``cancel()`` returned True (a newer request arrived)."""


def _finite_positive(value: Any) -> bool:
    return (not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
            and math.isfinite(value) and value > 0)


@dataclass(frozen=True)
class Settings:
    """Everything a reconstruction depends on, besides the session and its calibration.

    One typed object for the CLI, the viewer, the widgets and batch work.
    :meth:`validate` raises :class:`SettingsError` naming the field.

    Attributes
    ----------
    voxel_size : float, mm
    threshold : float or None
        Silhouette threshold for every view, grey levels (background
        subtraction) or Delta E (a session keyed against a ``backdrop``);
        None = automatic per view (subtraction then keeps each view's dim
        rim: :func:`organlab.silhouette.grow_rim`, docs/silhouettes.md).
    method : {'hull', 'coloring', 'space_carving', 'photo'}
        ``'photo'``: patch NCC between neighbouring views (textured specimens; docs/coloring.md).
    hull : {'subvoxel', 'thesis'}
    color_threshold : float or None
        Photo-consistency threshold, grey levels (``'photo'``: the NCC gain); None = automatic (``'photo'``:
        :data:`organlab.coloring.DEFAULT_PHOTO_THRESHOLD`).
    tolerance : int
        Views allowed to disagree before a voxel is carved.
    finish : bool
        Repair, smooth and remesh the marching-cubes surface.
    measure : bool or None
        AAA measures; None = when the session's specimen is an AAA.
    roi : ((3,), (3,)) tuple of float, mm, or None
        The box carved, world frame; None = the session's ``roi``.
    refine_poses : {'auto', 'on', 'off'}
        Correct the poses from the silhouettes (:func:`organlab.poses.refine_poses`).
    joint_silhouettes : {'auto', 'on', 'off'}
        Segment every view again with the hull of all the views as a prior
        (:meth:`organlab.silhouette.SilhouetteModel.joint`: adds what the
        other views require and the colour does not deny, drops what no
        view explains); 'auto' (default): for a session keyed against a
        backdrop with >= 8 views (keyed views get its required rule and
        removal only); 'on' also for background subtraction (on the sample
        it changes 4 px and costs about 3 s CPU at 1 mm); see
        docs/silhouettes.md.

    Examples
    --------
    >>> s = Settings(voxel_size=2.0).replace(threshold=20.0)
    >>> Settings.from_dict(s.to_dict()) == s
    True
    >>> Settings(threshold=-1).validate()
    Traceback (most recent call last):
    ...
    organlab.errors.SettingsError: threshold must be a finite number > 0 (grey levels, or Delta E for a backdrop session), got -1
    """

    voxel_size: float = 1.0
    threshold: float | None = None
    method: str = "hull"
    hull: str = "subvoxel"
    color_threshold: float | None = None
    tolerance: int = 0
    finish: bool = True
    measure: bool | None = None
    roi: tuple | None = None
    refine_poses: str = "auto"  # 'auto' | 'on' | 'off' (organlab.poses.refine_poses)
    joint_silhouettes: str = "auto"  # 'auto' | 'on' | 'off' (SilhouetteModel.joint: every view's hull as a prior)

    def replace(self, **changes: Any) -> Settings:
        """A copy with some fields changed (validated)."""
        unknown = set(changes) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise SettingsError(sorted(unknown)[0], f"is not a setting; settings are {[f.name for f in dataclasses.fields(self)]}")
        return dataclasses.replace(self, **changes).validate()

    def to_dict(self) -> dict:
        """Plain JSON-able values (roi as two lists)."""
        d = dataclasses.asdict(self)
        if self.roi is not None:
            d["roi"] = [list(map(float, self.roi[0])), list(map(float, self.roi[1]))]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Settings:
        """Settings from :meth:`to_dict`'s form, validated; unknown keys are refused."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise SettingsError(sorted(unknown)[0], f"is not a setting; settings are {sorted(names)}")
        d = dict(d)
        if d.get("roi") is not None:
            try:
                d["roi"] = (tuple(float(v) for v in d["roi"][0]), tuple(float(v) for v in d["roi"][1]))
            except (TypeError, ValueError, IndexError):
                raise SettingsError("roi", f"must be two points (3 numbers each, mm), got {d['roi']!r}") from None
        return cls(**d).validate()

    def validate(self) -> Settings:
        """Check every field; returns ``self`` (raises :class:`SettingsError` naming the field)."""
        if not _finite_positive(self.voxel_size):
            raise SettingsError("voxel_size", f"must be a finite number of mm > 0, got {self.voxel_size!r}")
        if self.threshold is not None and not _finite_positive(self.threshold):
            raise SettingsError("threshold", "must be a finite number > 0 (grey levels, or Delta E for a backdrop "
                                f"session), got {self.threshold!r}")
        if self.method not in METHODS:
            raise SettingsError("method", f"must be one of {METHODS}, got {self.method!r}")
        if self.hull not in HULL_METHODS:
            raise SettingsError("hull", f"must be one of {HULL_METHODS}, got {self.hull!r}")
        if self.color_threshold is not None and not _finite_positive(self.color_threshold):
            raise SettingsError("color_threshold", f"must be a finite number of grey levels > 0, got {self.color_threshold!r}")
        if self.method == "photo" and self.color_threshold is not None and not self.color_threshold < 2:
            raise SettingsError("color_threshold", f"for method 'photo' is an NCC gain in (0, 2), got {self.color_threshold!r}")
        if isinstance(self.tolerance, bool) or not isinstance(self.tolerance, (int, np.integer)) or self.tolerance < 0:
            raise SettingsError("tolerance", f"must be an integer >= 0 (views), got {self.tolerance!r}")
        if not isinstance(self.finish, (bool, np.bool_)):
            raise SettingsError("finish", f"must be True or False, got {self.finish!r}")
        if self.measure is not None and not isinstance(self.measure, (bool, np.bool_)):
            raise SettingsError("measure", f"must be True, False or None (when the session is an AAA), got {self.measure!r}")
        if self.refine_poses not in POSE_MODES:
            raise SettingsError("refine_poses", f"must be one of {POSE_MODES}, got {self.refine_poses!r}")
        if self.joint_silhouettes not in JOINT_MODES:
            raise SettingsError("joint_silhouettes", f"must be one of {JOINT_MODES}, got {self.joint_silhouettes!r}")
        if self.roi is not None:
            try:
                lo, hi = (np.asarray(v, dtype=np.float64) for v in self.roi)
                ok = lo.shape == hi.shape == (3,) and np.isfinite(lo).all() and np.isfinite(hi).all() and (hi > lo).all()
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise SettingsError("roi", f"must be (min, max), 3 finite numbers each in mm, max > min, got {self.roi!r}")
        return self


#: The Settings fields each stage depends on, in the order the stages run.  A change
#: re-runs that stage and every stage after it; the earlier ones are kept.
DEPENDS: dict[str, tuple[str, ...]] = {
    "calibration": (),  # the Engine's calibration= / recalibrate= (fixed for an Engine)
    "silhouettes": ("threshold", "joint_silhouettes"),
    "poses": ("refine_poses",),  # the poses corrected from the silhouettes (organlab.poses), before carving
    "carving": ("voxel_size", "roi", "hull", "tolerance"),
    "coloring": ("method", "color_threshold"),
    "surface": ("finish", "measure"),
    "checks": (),
}

#: The stages, in the order they run.
STAGES: tuple[str, ...] = tuple(DEPENDS)

#: Grids up to this many voxels (0.75 mm on the sample's roi) measure the AAA while the surface is finished.
_CONCURRENT_MEASURES_VOXELS = 16_000_000


# ---------------------------------------------------------------- typed stage results
@dataclass(frozen=True)
class CalibrationStage:
    """The calibration used and the camera of every view.

    Attributes
    ----------
    calibration : organlab.calibration.Calibration
    how : str
        As :func:`organlab.calibration.calibration_for` says it was obtained.
    cameras : list of Camera, one per view
    seconds : float or None
        Time spent when a calibration was computed (None when reused or given).
    """

    calibration: Any
    how: str
    cameras: list
    seconds: float | None = None


class CarvingStage:
    """The carved voxel model.

    Attributes
    ----------
    grid : VoxelGrid
    occupancy : (nx, ny, nz) bool
        Given, or made from ``field`` when first read (``BandField.occupancy``): one byte per
        voxel of the grid (251 MB at 0.25 mm on the sample), so not held while the surface is
        finished and measured, which need only the band.
    field : organlab.carving.BandField or None
        The sub-voxel hull field (``hull='subvoxel'``).
    """

    def __init__(self, grid: VoxelGrid, occupancy: np.ndarray | None, field: Any = None) -> None:
        if occupancy is None and field is None:
            raise ValueError("CarvingStage needs an occupancy or a field")
        self.grid, self._occupancy, self.field = grid, occupancy, field

    @property
    def occupancy(self) -> np.ndarray:
        if self._occupancy is None:
            self._occupancy = self.field.occupancy()
        return self._occupancy

    def __repr__(self) -> str:
        return f"CarvingStage(grid={self.grid!r}, field={self.field!r})"


@dataclass(frozen=True)
class ColoringStage:
    """What voxel colouring kept (``method`` other than ``'hull'``).

    Attributes
    ----------
    occupancy : (nx, ny, nz) bool
    colors : (nx, ny, nz, 3) uint8
    colored : (nx, ny, nz) bool
    threshold : float
        The threshold used (the measured one when automatic).
    info : dict
        The report's ``coloring`` entry (:func:`organlab.coloring.report_entry`).
    """

    occupancy: np.ndarray
    colors: np.ndarray
    colored: np.ndarray
    threshold: float
    info: dict


@dataclass(frozen=True)
class SurfaceStage:
    """The surface and the measures.

    Attributes
    ----------
    raw_mesh : Mesh
        Marching cubes of the field (or of the coloured occupancy).
    mesh : Mesh
        The finished surface (``raw_mesh`` when ``finish`` is off).
    steps : dict or None
        :func:`organlab.surface.finish_surface`'s report, with ``pixel_footprint_mm``.
    aaa : organlab.surface.AAAMeasures or None
    aaa_error : str or None
        Why an AAA session was not measured.
    """

    raw_mesh: Any
    mesh: Any
    steps: dict | None = None
    aaa: Any = None
    aaa_error: str | None = None

    def to_dict(self) -> dict:
        """The report's keys of this stage."""
        d: dict = {"raw_mesh_volume_mm3": self.raw_mesh.volume}
        if self.steps is not None:
            d["surface"] = self.steps
        if self.aaa is not None:
            d["aaa"] = self.aaa.summary()
        if self.aaa_error is not None:
            d["aaa_error"] = self.aaa_error
        return d


@dataclass(frozen=True)
class AgreementFigures:
    """The agreement figures every face shows: one mean, one ranking.

    The views are ranked by :attr:`ViewAgreement.worst` (:func:`organlab.agreement.worst_views`:
    the largest unexplained width of outline first, the figure whose limit flags a view),
    and the report, the CLI summary and the viewer panel all read this object.

    Attributes
    ----------
    names : tuple of str
        The views' image names.
    iou : tuple of float
        IoU of each view's silhouette with the model's projection.
    disagreement : tuple of float
        Fraction of each silhouette unexplained beyond the outline tolerance.
    ranking : tuple of int
        View indices, worst first.
    mean_iou : float
    """

    names: tuple
    iou: tuple
    disagreement: tuple
    ranking: tuple
    mean_iou: float

    @classmethod
    def from_agreement(cls, agr: ViewAgreement, names: Sequence[str]) -> AgreementFigures:
        iou = tuple(float(v["iou"]) for v in agr.views)
        return cls(tuple(names), iou, tuple(float(v["disagreement"]) for v in agr.views), tuple(int(i) for i in agr.worst),
                   float(np.mean(iou)) if iou else float("nan"))

    @classmethod
    def from_report(cls, report: dict) -> AgreementFigures | None:
        """The figures of a ``report.json`` (None when it has no agreement)."""
        rows = report.get("views", [])
        if not report.get("agreement") or not rows or any("agreement" not in r for r in rows):
            return None
        names = tuple(r["image"] for r in rows)
        iou = tuple(float(r["agreement"]["iou"]) for r in rows)
        dis = tuple(float(r["agreement"]["disagreement"]) for r in rows)
        ranking = tuple(worst_views([r["agreement"] for r in rows]))  # view_agreement's ranking
        mean = report["agreement"].get("mean_iou", float(np.mean(iou)))
        return cls(names, iou, dis, ranking, float(mean))

    def subset(self, indices: Sequence[int]) -> AgreementFigures:
        """The figures of some views only (in this order), ranked the same way."""
        idx = [int(i) for i in indices]
        dis = tuple(self.disagreement[i] for i in idx)
        iou = tuple(self.iou[i] for i in idx)
        rank = {v: k for k, v in enumerate(self.ranking)}
        return AgreementFigures(tuple(self.names[i] for i in idx), iou, dis,
                                tuple(sorted(range(len(idx)), key=lambda k: rank[idx[k]])), float(np.mean(iou)))

    @property
    def worst(self) -> int:
        """Index of the worst view."""
        return self.ranking[0]

    def line(self, label: Callable[[int], str] | None = None) -> str:
        """``mean IoU 0.990, worst view NAME: 0.21 % unexplained (IoU 0.987)``."""
        w = self.worst
        name = self.names[w] if label is None else label(w)
        return (f"mean IoU {self.mean_iou:.3f}, worst view {name}: {100 * self.disagreement[w]:.2f} % unexplained "
                f"(IoU {self.iou[w]:.3f})")

    def to_dict(self) -> dict:
        return {"mean_iou": self.mean_iou, "worst_views": [self.names[i] for i in self.ranking[:3]]}


@dataclass(frozen=True)
class ChecksStage:
    """The trust checks and the report.

    Attributes
    ----------
    agreement : organlab.agreement.ViewAgreement
    figures : AgreementFigures
    report : dict
        The content of ``report.json``.
    """

    agreement: ViewAgreement
    figures: AgreementFigures
    report: dict


# ---------------------------------------------------------------- the result
@dataclass
class Reconstruction:
    """Everything a run computed (:meth:`Engine.run`, :func:`organlab.pipeline.reconstruct`).

    Attributes
    ----------
    session : Session or None
        None for a result read back by :meth:`load`.
    grid : VoxelGrid
    occupancy : (nx, ny, nz) bool
        The carved (and coloured) voxel model.
    mesh : organlab.surface.Mesh or None
    cameras : list of Camera
    silhouettes : list of organlab.silhouette.Silhouette
    report : dict or None
        The content of ``report.json``.
    field : organlab.carving.BandField or None
        Sub-voxel field whose 0.5 level is the surface (``hull='subvoxel'``);
        ``np.asarray(field)`` is the dense ``(nx, ny, nz)`` float32 field.
    colors : (nx, ny, nz, 3) uint8 or None
        Voxel colours (``method='coloring'``).
    calibration : organlab.calibration.Calibration
    raw_mesh : Mesh or None
        The marching-cubes mesh before finishing.
    aaa : organlab.surface.AAAMeasures or None
    settings : Settings or None
    agreement : AgreementFigures or None
    aaa_error : str or None
    color_threshold : float or None
        The colour threshold colouring used.
    timings : dict of str -> float
        Seconds per stage run (a kept stage: the time it took when it ran).
    views : list of int
        The indices of the views reconstructed (``Engine(views=...)``; every view by default).
    coloring : dict or None
        The colouring's figures (the report's ``coloring`` entry).

    A run stopped by ``until=`` leaves the fields of the later stages None.
    """

    session: Any
    grid: Any
    occupancy: Any
    mesh: Any
    cameras: list
    silhouettes: list
    report: dict | None
    field: Any = None
    colors: np.ndarray | None = None
    calibration: Any = None
    raw_mesh: Any = None
    aaa: Any = None
    settings: Settings | None = None
    agreement: AgreementFigures | None = None
    aaa_error: str | None = None
    color_threshold: float | None = None
    timings: dict = dataclasses.field(default_factory=dict)
    views: list | None = None
    coloring: dict | None = None

    @property
    def masks(self) -> list:
        """The silhouettes' masks, (H, W) bool each."""
        return [s.mask for s in self.silhouettes]

    def save(self, folder: str | Path, *, atomic: bool = True) -> dict:
        """Write ``report.json``, ``voxels.npz``, ``mesh.ply``, ``mesh.stl`` (and ``calibration.json``).

        ``calibration.json`` is the calibration used, when it was fitted from
        board images.  With ``atomic`` the files go into a temporary folder
        that replaces ``folder`` once all are written
        (:func:`organlab.preflight.atomic_output_dir`).

        Returns
        -------
        dict of str -> Path
        """
        if self.report is None or self.mesh is None:
            raise OrganlabError("an unfinished reconstruction (run with until=) has no report or mesh to save")
        if atomic:
            with atomic_output_dir(folder) as tmp:
                paths = self.save(tmp, atomic=False)
            return {k: Path(folder) / p.name for k, p in paths.items()}
        out = Path(folder)
        out.mkdir(parents=True, exist_ok=True)
        paths = {k: out / n for k, n in (("report", "report.json"), ("voxels", "voxels.npz"), ("ply", "mesh.ply"),
                                         ("stl", "mesh.stl"))}
        arrays = {
            "occupancy": np.ascontiguousarray(self.occupancy, dtype=bool),
            "origin_mm": np.asarray(self.grid.origin, dtype=np.float64),
            "voxel_size_mm": np.float64(self.grid.voxel_size),
        }
        if self.colors is not None:
            arrays["colors"] = self.colors
        if isinstance(self.field, BandField):  # the band only: the file grows with the surface, not the volume
            arrays.update(self.field.to_arrays(prefix="field_"))
        elif self.field is not None:  # a dense field (hull_field(sparse=False)), as earlier versions stored it
            arrays["field"] = np.asarray(self.field, dtype=np.float32)
        _savez_deflate1(paths["voxels"], arrays)
        surface.write_ply(paths["ply"], self.mesh)
        surface.write_stl(paths["stl"], self.mesh)
        write_json(paths["report"], self.report)
        cal = self.calibration
        if cal is not None and (cal.intrinsics is not None or cal.turntable is not None):
            paths["calibration"] = cal.save(out / "calibration.json")
        return paths

    @classmethod
    def load(cls, folder: str | Path, *, session: Session | None = None, mesh: bool = True) -> Reconstruction:
        """A result folder written by :meth:`save` (``organlab reconstruct --out``) read back.

        The voxels, field and colours from ``voxels.npz``, the mesh from
        ``mesh.ply``, the report from ``report.json`` (its settings as
        :attr:`settings`).  Cameras and silhouettes are not stored: empty.
        Every file is read through :mod:`organlab.validate`: ``voxels.npz``
        without pickles, its decompressed size checked against the memory
        available before decoding, every array typed, shaped and finite;
        ``report.json`` strict JSON with the keys read here typed; the mesh
        checked by :func:`organlab.surface.read_ply`.  With ``mesh=False``
        ``mesh.ply`` is neither needed nor read (:attr:`mesh` None): ``organlab
        mesh`` makes its surface from the voxels.

        Raises
        ------
        OrganlabError
            One line naming the missing, unreadable or malformed file (and the
            array or key).

        Examples
        --------
        >>> import tempfile
        >>> from organlab.engine import Reconstruction, Settings, run
        >>> out = tempfile.mkdtemp() + "/out"
        >>> _ = run("sample_sessions/aaa_phantom", Settings(voxel_size=4.0, finish=False)).save(out)
        >>> rec = Reconstruction.load(out)
        >>> rec.grid.voxel_size, rec.mesh.is_watertight
        (4.0, True)
        """
        folder = Path(folder)
        fix = "rewrite it with 'organlab reconstruct'"
        if not folder.is_dir():
            raise OrganlabError(f"{folder}: {'is a file, not' if folder.exists() else 'no such'} result folder; "
                                f"write one with 'organlab reconstruct SESSION --out {folder}'")
        vox, ply, rep = folder / "voxels.npz", folder / "mesh.ply", folder / "report.json"
        for p in (vox, ply) if mesh else (vox,):
            if not p.is_file():
                raise OrganlabError(f"{p}: missing; write the folder with 'organlab reconstruct SESSION --out {folder}'")
        arrays = validate.read_npz(vox, fix=fix, max_bytes=available_memory())
        occ, grid = _result_grid(arrays, vox, fix)
        field = None
        if "field_block" in arrays or "field_states" in arrays:
            field = BandField.from_arrays(arrays, grid, prefix="field_", source=str(vox))
        elif "field" in arrays:
            field = arrays["field"]
            if field.shape != occ.shape or field.dtype.kind != "f" or not np.all(np.isfinite(field)):
                raise OrganlabError(f"{vox}: field: {field.dtype} {field.shape}, expected finite floats of the "
                                    f"occupancy's shape {occ.shape}; {fix}")
        colors = arrays.get("colors")
        if colors is not None and (colors.dtype != np.uint8 or colors.shape != (*occ.shape, 3)):
            raise OrganlabError(f"{vox}: colors: {colors.dtype} {colors.shape}, expected uint8 {(*occ.shape, 3)}; {fix}")
        report = _read_report(rep, fix) if rep.is_file() else {}
        surf = read_ply(ply) if mesh else None
        lo, hi = grid.bounds
        settings = Settings(voxel_size=grid.voxel_size, method=report.get("method", "hull"),
                            hull=report.get("hull", "subvoxel"), roi=(tuple(lo), tuple(hi)))
        coloring = report.get("coloring") or {}
        return cls(session, grid, occ, surf, [], [], report, field, colors, None,
                   settings=settings, agreement=AgreementFigures.from_report(report),
                   color_threshold=coloring.get("threshold"), aaa_error=report.get("aaa_error"))

    def surface_volume(self) -> np.ndarray:
        """The volume whose 0.5 level is the surface, ``grid.shape`` float32: the sub-voxel field when
        there is one and no colouring carved the occupancy, else the occupancy as 0/1 (what
        ``organlab mesh`` meshes)."""
        if self.field is not None and self.colors is None:
            return np.asarray(self.field.dense() if isinstance(self.field, BandField) else self.field, dtype=np.float32)
        return np.asarray(self.occupancy, dtype=np.float32)


def _savez_deflate1(path, arrays):
    """``np.savez_compressed(path, **arrays)`` at deflate level 1 instead of 6: the same ``.npz`` (a zip of
    ``.npy`` files, read back by ``np.load`` bit for bit), a larger file, less CPU.  The sample at 0.25 mm
    (250 MB occupancy): 3.20 -> 4.35 MB of file, 2.00 -> 0.78 s CPU; the command's writing step 2.33 -> 0.62 s."""
    import zipfile

    with zipfile.ZipFile(path, mode="w", compression=zipfile.ZIP_DEFLATED, compresslevel=1, allowZip64=True) as z:
        for key, value in arrays.items():
            with z.open(key + ".npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(value), allow_pickle=False)


def _result_grid(arrays, path, fix):
    """The occupancy and grid of a ``voxels.npz``'s arrays, checked."""
    for key in ("occupancy", "origin_mm", "voxel_size_mm"):
        if key not in arrays:
            raise OrganlabError(f"{path}: no {key!r} array; {fix}")
    occ = arrays["occupancy"]
    if occ.ndim != 3 or occ.dtype.kind not in "bui" or 0 in occ.shape:
        raise OrganlabError(f"{path}: occupancy: {occ.dtype} {occ.shape}, expected (nx, ny, nz) booleans; {fix}")
    if occ.dtype != bool and occ.size and (occ.min() < 0 or occ.max() > 1):
        raise OrganlabError(f"{path}: occupancy: values other than 0 and 1; {fix}")
    origin = validate.array(arrays["origin_mm"], (3,), "origin_mm", where=str(path), lo=-1e6, hi=1e6)
    vs = arrays["voxel_size_mm"]
    vs = validate.number(vs[()] if vs.shape == () else None, "voxel_size_mm", where=str(path), lo=1e-4, hi=1e4)
    return occ.astype(bool), VoxelGrid(tuple(float(v) for v in origin), vs, occ.shape)


def _read_report(path, fix):
    """``report.json`` read strictly, the keys :meth:`Reconstruction.load` and the faces use typed."""
    report = validate.read_json(path, fix=fix)
    where = str(path)

    def bad(key, why):
        return OrganlabError(f"{path}: {key}: {why}; {fix}")

    if not isinstance(report, dict):
        raise bad("(top level)", "must be an object")
    if report.get("method", "hull") not in METHODS:
        raise bad("method", f"must be one of {', '.join(METHODS)}, got {validate.printable(report.get('method'))!r}")
    if report.get("hull", "subvoxel") not in HULL_METHODS:
        raise bad("hull", f"must be one of {', '.join(HULL_METHODS)}, got {validate.printable(report.get('hull'))!r}")
    for key in ("session", "aaa_error"):
        if report.get(key) is not None:
            validate.string(report[key], key, where=where)
    for key in ("coloring", "agreement", "calibration", "grid"):
        if report.get(key) is not None and not isinstance(report[key], dict):
            raise bad(key, "must be an object")
    validate.number((report.get("coloring") or {}).get("threshold"), "coloring.threshold", where=where, lo=0,
                    required=False)
    if (report.get("agreement") or {}).get("mean_iou") is not None:
        validate.number(report["agreement"]["mean_iou"], "agreement.mean_iou", where=where, lo=0, hi=1)
    if not isinstance(report.get("warnings", []), list) or not all(isinstance(w, str) for w in report.get("warnings", [])):
        raise bad("warnings", "must be a list of texts")
    views = report.get("views", [])
    if not isinstance(views, list) or not all(isinstance(v, dict) for v in views):
        raise bad("views", "must be a list of objects")
    agreed = [v for v in views if "agreement" in v]
    for i, v in enumerate(views):
        key = f"views[{i}]"
        validate.string(v.get("image"), f"{key}.image", where=where)
        validate.number(v.get("silhouette_threshold"), f"{key}.silhouette_threshold", where=where, required=False)
        if "agreement" in v:
            a = v["agreement"]
            if not isinstance(a, dict):
                raise bad(f"{key}.agreement", "must be an object")
            validate.number(a.get("iou"), f"{key}.agreement.iou", where=where, lo=0, hi=1)
            validate.number(a.get("disagreement"), f"{key}.agreement.disagreement", where=where, lo=0, hi=1)
            for k in ("disagreement_width_px", "unexplained_silhouette_px"):
                validate.number(a.get(k), f"{key}.agreement.{k}", where=where, lo=0, required=False)
    if agreed and len(agreed) != len(views):
        raise bad("views", "some views have an agreement entry and some do not")
    return report


# ---------------------------------------------------------------- the engine
class _Clock:
    """Per-stage progress bars (``progress(stage) -> bar``) and the cancel check."""

    def __init__(self, progress, cancel):
        self.progress = progress or (lambda stage: NullProgress())
        self.cancel = cancel

    def check(self):
        if self.cancel is not None and self.cancel():
            raise Cancelled

    def bar(self, stage):
        """A ``bar(done, total)`` that also polls ``cancel``; call ``.close()`` after."""
        inner = self.progress(stage)
        clock = self

        class Bar:
            def __call__(self, done, total):
                clock.check()
                inner(done, total)

            def close(self):
                inner.close()

        return Bar()


def pixel_footprint(cameras: Sequence, grid: VoxelGrid) -> float:
    """Median size of a pixel at the centre of the voxel space over the views, mm.

    What the silhouettes resolve at the specimen: the finished surface's edges
    need not be shorter (``finish_surface(min_edge_mm=...)``).
    """
    lo, hi = grid.bounds
    c = (np.asarray(lo, float) + np.asarray(hi, float)) / 2
    return float(np.median([cam.pixel_footprint(c) for cam in cameras]))


class Engine:
    """The stages of one session, run on demand and kept for the next run.

    Parameters
    ----------
    session : Session or str or Path
    calibration : Calibration or str or Path, optional
        Use this calibration (checked against the session) instead of the
        session's own (:func:`organlab.calibration.calibration_for`).
    recalibrate : bool
        Calibrate from the board images even when ``calibration.json`` matches.
    images : sequence of (H, W, 3) uint8, optional
        The images of ``views``, already read (read from the session otherwise).
    views : sequence of int, optional
        Reconstruct from these views only (default every view), in this order.
    max_memory : int, optional
        Bytes the voxel grid may take (default the memory available now;
        :func:`organlab.preflight.check_grid_memory`).
    cameras : sequence of Camera, optional
        The views' cameras, given: no calibration stage runs.
    silhouettes : sequence of Silhouette, optional
        The views' silhouettes, given: ``Settings.threshold`` does not apply.
    mode, background : str
        How the silhouettes are found (:class:`organlab.silhouette.SilhouetteModel`):
        colour or grey difference, median or mean background model.

    :meth:`from_views` makes an engine of views without a session (the
    carving tuner's): cameras and silhouettes given, the roi in the settings.

    Attributes
    ----------
    session : Session or None
    views : list of int
    computed : dict of str -> int
        How many times each stage ran (the rest came from the cache).
    """

    def __init__(self, session: Session | str | Path | None, *, calibration: Any = None, recalibrate: bool = False,
                 images: Sequence[np.ndarray] | None = None, views: Sequence[int] | None = None,
                 max_memory: int | None = None, cameras: Sequence | None = None,
                 silhouettes: Sequence[Silhouette] | None = None, mode: str = "color", background: str = "median"):
        self._model_options = {"mode": mode, "background": background}
        if session is None:
            if cameras is None or silhouettes is None:
                raise SettingsError("session", "is needed unless the cameras and the silhouettes are given")
            self.session = None
            n = len(cameras)
        else:
            self.session = session if isinstance(session, Session) else load_session(session)
            s = self.session
            if not s.views:
                raise SessionError(f"{s.json_path}: views: the session has no views to reconstruct "
                                   "(calibration-only session)")
            n = len(s.views)
        self.views = list(range(n)) if views is None else [int(i) for i in views]
        bad = [i for i in self.views if not 0 <= i < n]
        if bad or not self.views:
            raise SettingsError("views", f"must be indices of the {n} views, got {views!r}")
        for what, given in (("images", images), ("cameras", cameras), ("silhouettes", silhouettes)):
            if given is not None and len(given) != len(self.views):
                raise SettingsError(what, f"must be one per view: got {len(given)} for {len(self.views)} views")
        self._cameras = None if cameras is None else list(cameras)
        self._silhouettes = None if silhouettes is None else list(silhouettes)
        self._calibration = calibration
        self._recalibrate = bool(recalibrate)
        self._images = None if images is None else list(images)
        self.max_memory = max_memory
        self._model = None
        self._cache: dict[str, tuple[tuple, Any]] = {}
        self.computed = {name: 0 for name in STAGES}
        self.timings: dict[str, float] = {}
        self.joint_summary: dict | None = None  # the joint silhouette step's last run (None: it did not run)
        self._until: str | None = None  # the running run()'s last stage
        self._hull_job: tuple | None = None  # (raw mesh, cameras, silhouettes, future of their hull_masks)
        self._field_job: _FieldJob | None = None  # the hull field started beside the poses check (_run_poses)

    @classmethod
    def from_views(cls, images: Sequence[np.ndarray] | None, silhouettes: Sequence[Silhouette], cameras: Sequence, *,
                   max_memory: int | None = None) -> Engine:
        """An engine of views without a session: the silhouettes and cameras given, ``Settings.roi`` needed.

        ``images`` (one per view) are needed by colouring only.  Its runs have
        no report (nothing of a session to write); the agreement is measured.
        """
        return cls(None, images=images, cameras=cameras, silhouettes=silhouettes, max_memory=max_memory)

    # ------------------------------------------------------------ what does not depend on the settings
    @property
    def images(self) -> list:
        """The views' images, read once (colouring needs them again)."""
        if self._images is None:
            if self.session is None:
                raise SettingsError("images", "are needed for colouring (method other than 'hull')")
            s = self.session
            self._images = [s.read(s.views[i].image, key=f"views[{i}].image") for i in self.views]
        return self._images

    @property
    def silhouette_model(self) -> SilhouetteModel:
        """The views prepared for silhouettes at any threshold (background or backdrop keying), built once."""
        if self._model is None:
            self._model = SilhouetteModel.from_session(self.session, images=self.images, views=self.views,
                                                       **self._model_options)
        return self._model

    @property
    def names(self) -> list:
        """The views' image names, relative to the session folder (``views[i]`` without a session)."""
        if self.session is None:
            return [f"views[{i}]" for i in self.views]
        return [self.session.relpath(self.session.views[i].image) for i in self.views]

    def cameras(self) -> list:
        """The camera of every view (the calibration stage, run or kept)."""
        return self._stage("calibration", Settings(), _Clock(None, None)).cameras

    def roi(self, settings: Settings) -> tuple:
        """The box carved: ``settings.roi`` or the session's."""
        if settings.roi is not None:
            return tuple(tuple(float(v) for v in p) for p in settings.roi)
        if self.session is None:
            raise SettingsError("roi", "is needed: no session gives one")
        return (tuple(float(v) for v in self.session.roi_min), tuple(float(v) for v in self.session.roi_max))

    def grid(self, settings: Settings) -> VoxelGrid:
        lo, hi = self.roi(settings)
        return VoxelGrid.from_roi(lo, hi, settings.voxel_size)

    # ------------------------------------------------------------ running
    def key(self, stage: str, settings: Settings) -> tuple:
        """The settings a stage's result depends on, its own and every earlier stage's."""
        fields = []
        for name in STAGES:
            fields += DEPENDS[name]
            if name == stage:
                break
        return tuple((f, _hashable(getattr(settings, f))) for f in fields)

    def cached(self, stage: str, settings: Settings) -> bool:
        """Whether ``stage``'s result for these settings is kept (a run would not recompute it)."""
        hit = self._cache.get(stage)
        return hit is not None and hit[0] == self.key(stage, settings)

    def kept(self, until: str) -> dict:
        """The kept results of the stages up to ``until``, to go on from them in another Engine (:meth:`keep`).

        Returns
        -------
        dict of str -> (key, result, seconds)
            Per kept stage: the settings its result depends on (:meth:`key`),
            its typed result and its time (None when not timed).  Plain data: a
            sweep sends it from the task that computed a threshold's silhouettes
            and poses to the tasks that carve at that threshold.
        """
        if until not in STAGES:
            raise SettingsError("until", f"must be one of {STAGES}, got {until!r}")
        names = STAGES[:STAGES.index(until) + 1]
        return {n: (*self._cache[n], self.timings.get(n)) for n in names if n in self._cache}

    def keep(self, kept: dict) -> None:
        """Take stage results from another Engine's :meth:`kept` as if computed here.

        The other engine must have had the same session, calibration, images
        and views (the keys hold the settings only); a later :meth:`run` re-uses
        each kept stage whose key matches its settings, as for its own.
        """
        unknown = [n for n in kept if n not in STAGES]
        if unknown:
            raise SettingsError("kept", f"holds unknown stages {unknown}; stages are {STAGES}")
        for name in STAGES:
            if name in kept:
                key, result, seconds = kept[name]
                self._cache[name] = (tuple(key), result)
                if seconds is None:
                    self.timings.pop(name, None)
                else:
                    self.timings[name] = seconds

    def run(self, settings: Settings | None = None, *, on_stage: Callable[[str, Any], None] | None = None,
            cancel: Callable[[], bool] | None = None, until: str | None = None,
            progress: Callable[[str], Any] | None = None) -> Reconstruction:
        """Run the stages, re-using every kept stage whose inputs did not change.

        Parameters
        ----------
        settings : Settings, optional
            Default ``Settings()``.
        on_stage : callable(name, result), optional
            Called after each stage with its typed result (:class:`CalibrationStage`,
            list of Silhouette, :class:`CarvingStage`, :class:`ColoringStage` or
            None for ``method='hull'``, :class:`SurfaceStage`, :class:`ChecksStage`);
            also ``on_stage('mesh', raw_mesh)`` as soon as marching cubes is done,
            before the surface is finished (the viewer shows it first).
        cancel : callable() -> bool, optional
            Polled between stages and inside the long ones; True raises :class:`Cancelled`.
        until : str, optional
            Stop after this stage (one of :data:`STAGES`); later fields are None.
        progress : callable(stage) -> bar, optional
            Factory of per-stage progress bars (``bar(done, total)``, ``bar.close()``).

        Returns
        -------
        Reconstruction
        """
        settings = (Settings() if settings is None else settings).validate()
        if until is not None and until not in STAGES:
            raise SettingsError("until", f"must be one of {STAGES}, got {until!r}")
        clock = _Clock(progress, cancel)
        self._preflight(settings)
        self._until, self._hull_job = until, None
        notify = on_stage or (lambda name, result: None)
        out = {}
        try:
            for name in STAGES:
                clock.check()
                out[name] = self._stage(name, settings, clock, out, notify)
                notify(name, out[name])
                if name == until:
                    break
        finally:  # a field started beside the poses check and not taken (an error, a cancel): stopped
            job, self._field_job = self._field_job, None
            if job is not None:
                job.stop.set()
        return self._reconstruction(settings, out)

    def _preflight(self, settings):
        if self._silhouettes is not None and settings.threshold is not None:
            raise SettingsError("threshold", "does not apply: the silhouettes are given")
        lo, hi = self.roi(settings)
        where = "the views" if self.session is None else str(self.session.json_path)
        check_grid_memory(lo, hi, settings.voxel_size, max_memory=self.max_memory, method=settings.method,
                          tolerance=int(settings.tolerance), where=where)
        if self.session is not None:  # the decoded views too, from their headers (organlab.preflight)
            check_image_memory(self.session.image_size, len(self.views), max_memory=self.max_memory, where=where)

    def _stage(self, name, settings, clock, out=None, notify=None):
        key = self.key(name, settings)
        hit = self._cache.get(name)
        if hit is not None and hit[0] == key:
            return hit[1]
        t0 = time.perf_counter()
        result = getattr(self, f"_run_{name}")(settings, clock, out or {}, notify or (lambda n, r: None))
        # done (not cancelled): the kept results after it are stale (their keys hold the old settings)
        for later in STAGES[STAGES.index(name):]:
            self._cache.pop(later, None)
            self.timings.pop(later, None)
        if name == "calibration":  # timed only when a calibration was computed
            if result.seconds is not None:
                self.timings[name] = result.seconds
        elif result is not None:  # (no colouring for method 'hull': not timed)
            self.timings[name] = time.perf_counter() - t0
        self.computed[name] += 1
        self._cache[name] = (key, result)
        return result

    # ------------------------------------------------------------ the stages
    def _run_calibration(self, settings, clock, out, notify):
        if self._cameras is not None:
            return CalibrationStage(None, "given", list(self._cameras))
        bar = None

        def progress(done, total):
            nonlocal bar
            clock.check()
            bar = bar or clock.progress("calibration")
            bar(done, total)

        t0 = time.perf_counter()
        cal, how = calibration_for(self.session, calibration=self._calibration, recalibrate=self._recalibrate,
                                   progress=progress)
        seconds = time.perf_counter() - t0 if (how == "computed" or how.startswith("recomputed")) else None
        if bar is not None:
            bar.close()
        every = cal.cameras(self.session)
        return CalibrationStage(cal, how, [every[i] for i in self.views], seconds)

    def _run_silhouettes(self, settings, clock, out, notify):
        if self._silhouettes is not None:
            return list(self._silhouettes)
        bar = clock.bar("silhouettes")
        sils = self.silhouette_model.silhouettes(threshold=settings.threshold, progress=bar)
        bar.close()
        mode = settings.joint_silhouettes
        if mode == "on" or (mode == "auto" and self.silhouette_model.joint_applies()):
            clock.check()
            sils, self.joint_summary = self.silhouette_model.joint(sils, out["calibration"].cameras,
                                                                   self.roi(Settings()))
        else:
            self.joint_summary = None
        return sils

    def _run_poses(self, settings, clock, out, notify):
        """:func:`organlab.poses.refine_poses` on every view of a session (None for some views or no session)."""
        cal = out["calibration"]
        if self.session is None or len(self.views) != len(self.session.views):
            return None  # the table angles and the gate need the whole turn
        # the images and the empty scene that made the silhouettes: sub-pixel outlines for the tangents
        model = self._model if self._silhouettes is None else None
        keyed = model is None or model.keyed or model.background is None
        self._field_job = self._start_field(settings, clock, out)
        return refine_poses(self.session, cal.calibration, out["silhouettes"], mode=settings.refine_poses,
                            cameras=cal.cameras, names=list(self.names), images=None if keyed else model.images,
                            background=None if keyed else model.background)

    def _run_carving(self, settings, clock, out, notify):
        sils, cameras = out["silhouettes"], _cameras(out)
        grid = self.grid(settings)
        bar = clock.bar("carving")
        job, self._field_job = self._field_job, None
        if job is not None and not job.fits(sils, cameras, grid, settings.tolerance):
            job.stop.set()  # the poses check moved the cameras: carved again with them
            job = None
        if settings.hull == "thesis":
            occupancy, field = carve(sils, cameras, grid, tolerance=settings.tolerance), None
        elif job is not None:  # the field of these very silhouettes, cameras, grid and tolerance, started beside the check
            field, occupancy = job.future.result(), None
        else:  # the field in a narrow band about the surface: cost grows with the surface, not the volume
            field = hull_field(sils, cameras, grid, tolerance=settings.tolerance, progress=bar, sparse=True)
            occupancy = None  # made when first read (CarvingStage.occupancy): after the surface
        bar(len(cameras), len(cameras))
        bar.close()
        if not (field.n_inside() if occupancy is None else occupancy.any()):
            where = "the views" if self.session is None else self.session.json_path
            raise SessionError(
                f"{where}: carving left no voxel: the silhouettes do not agree with the cameras "
                "(check the calibration, the roi and the threshold)"
            )
        return CarvingStage(grid, occupancy, field)

    def _start_field(self, settings, clock, out):
        """The hull field of the calibration's cameras started on a thread beside the poses check ('auto'), or None.

        The check mostly finds the poses right (every slider move of the viewer re-checks them): the carving
        then takes this field, computed with the very cameras it carves with, instead of starting it after
        the check (:meth:`_run_carving` takes it only when the check left the cameras as they were; else it
        stops it and carves with the corrected ones).  Small grids only (as the measures beside the finishing):
        when the check goes on to refine, the field runs beside the fits to its end, unused.
        """
        if not SPECULATIVE_FIELD or settings.refine_poses != "auto" or settings.hull == "thesis":
            return None
        if STAGES.index(self._until or STAGES[-1]) < STAGES.index("carving"):
            return None
        sils, cameras, grid = out["silhouettes"], list(out["calibration"].cameras), self.grid(settings)
        if grid.n_voxels > _CONCURRENT_MEASURES_VOXELS:  # a field lost to a correction costs up to 2.5 s (0.25 mm)
            return None
        stop = threading.Event()

        def progress(done, total):  # after each view's distance image
            if stop.is_set():
                raise Cancelled
            clock.check()

        pool = ThreadPoolExecutor(1, thread_name_prefix="organlab-field")
        future = pool.submit(hull_field, sils, cameras, grid, tolerance=settings.tolerance, progress=progress,
                             sparse=True)
        pool.shutdown(wait=False)
        return _FieldJob(sils, cameras, grid, int(settings.tolerance), future, stop)

    def _run_coloring(self, settings, clock, out, notify):
        if settings.method == "hull":
            return None
        carved, sils, cameras = out["carving"], out["silhouettes"], _cameras(out)
        kind = "voxel_coloring" if settings.method == "coloring" else "space_carving"
        bar = clock.bar("coloring")
        if settings.method == "photo":
            extra = {} if settings.color_threshold is None else {"threshold": settings.color_threshold}
            res = photo_carve(self.images, cameras, carved.occupancy, carved.grid, masks=[s.mask for s in sils],
                              progress=bar, **extra)
            bar.close()
            return ColoringStage(res.occupancy, res.colors, res.colored, float(res.threshold),
                                 report_entry(res, carved.occupancy, carved.grid))
        res = color_voxels(self.images, cameras, carved.occupancy, carved.grid, method=kind,
                           masks=[s.mask for s in sils], progress=bar,
                           threshold="auto" if settings.color_threshold is None else settings.color_threshold,
                           **PIPELINE_OPTIONS.resolve())
        bar.close()
        return ColoringStage(res.occupancy, res.colors, res.colored, float(res.threshold),
                             report_entry(res, carved.occupancy, carved.grid))

    def _run_surface(self, settings, clock, out, notify):
        carved, colored, cameras = out["carving"], out["coloring"], _cameras(out)
        grid = carved.grid
        bar = clock.bar("surface")
        # after colouring, the surface is the coloured voxel model's: the hull field knows
        # nothing of the voxels colouring carved, and setting them outside in the field
        # moved the surface inward by up to a voxel wherever colouring carved a surface voxel
        if colored is not None:
            surface_of = colored.occupancy
        else:
            surface_of = carved.occupancy if carved.field is None else carved.field
        raw = mesh_from_field(surface_of, grid)
        if colored is not None:
            raw = color_vertices(raw, colored.colors, colored.colored, grid)
        notify("mesh", raw)
        clock.check()
        mesh, steps = raw, None
        measuring = settings.measure or (settings.measure is None and self.is_aaa)
        # the AAA measures read the volume, finishing the mesh: independent, so measured in a second thread
        # while this one finishes (both spend much of their time outside the GIL: numba, scipy, pymeshlab;
        # the stage 0.70x in wall time at 1 mm).  Not on big grids, where their peaks would add up (at
        # 0.25 mm the measures take +415 MB, finishing +702 MB; at 1 mm about +20 MB)
        pool = aaa_job = None
        small = grid.n_voxels <= _CONCURRENT_MEASURES_VOXELS
        if measuring and settings.finish and small:
            pool = ThreadPoolExecutor(1, thread_name_prefix="organlab-aaa")
            aaa_job = pool.submit(_measure_beside, surface_of, grid)
        # the carved surface seen by every camera, for the agreement check (view_agreement's hull_masks), made on a
        # second thread: the carved surface has 6x the finished one's faces at 0.25 mm, and these masks were 0.8 s
        # of the check's 1.1 s CPU there.  Beside the finishing after the measures on small grids; on big ones after
        # the finishing (beside the measures), whose peak their 11 MB of masks and 12 MB of buffers would raise
        checking = settings.finish and STAGES.index(self._until or STAGES[-1]) >= STAGES.index("checks")
        if checking and small:
            pool = self._start_hull_masks(pool, raw, cameras, out["silhouettes"])
        if pool is not None:
            pool.shutdown(wait=False)  # its thread ends with the jobs; a cancelled run does not wait for them
        if settings.finish:
            footprint = pixel_footprint(cameras, grid)
            fin = finish_surface(raw, voxel_size=grid.voxel_size, min_edge_mm=footprint)
            mesh, steps = fin.mesh, {**fin.to_dict(), "pixel_footprint_mm": footprint}
            clock.check()
        if checking and not small:
            self._start_hull_masks(None, raw, cameras, out["silhouettes"]).shutdown(wait=False)
        aaa = error = None
        if measuring:
            try:
                aaa = measure_aaa(surface_of, grid) if aaa_job is None else aaa_job.result()
                if aaa_job is None:  # measured alone (a big grid, or no finishing): their freed arrays go back before the occupancy's
                    release_heap()
            except OrganlabError as e:
                if settings.measure:  # asked for: an error; automatic: noted in the report
                    raise
                error = str(e)
        bar(1, 1)
        bar.close()
        return SurfaceStage(raw, mesh, steps, aaa, error)

    def _run_checks(self, settings, clock, out, notify):
        s = self.session
        cal_stage, sils, carved = out["calibration"], out["silhouettes"], out["carving"]
        colored, surf = out["coloring"], out["surface"]
        cal, cameras, grid = cal_stage.calibration, _cameras(out), carved.grid
        occupancy = carved.occupancy if colored is None else colored.occupancy
        names = self.names
        turntable = None if s is None else [s.views[i].pose is None for i in self.views]
        agr = view_agreement(surf.mesh, cameras, sils, voxel_size=grid.voxel_size, names=names, hull_mesh=surf.raw_mesh,
                             turntable=turntable, hull_masks=self._made_hull_masks(surf.raw_mesh, cameras, sils))
        figures = AgreementFigures.from_agreement(agr, names)
        if s is None:  # views without a session: nothing of a session to report
            return ChecksStage(agr, figures, None)
        timings = {k: self.timings[k] for k in STAGES if k in self.timings and k not in ("checks", "poses")}
        report = _report(s, self.views, grid, occupancy, surf.mesh, cameras, cal, cal_stage.how, sils, timings,
                         settings)
        report.update(surf.to_dict())
        j = self.joint_summary
        report["joint_silhouettes"] = {"mode": settings.joint_silhouettes, "ran": j is not None,
                                       **({k: v for k, v in j.items() if k != "views"} if j else {}),
                                       **({"added_px": sum(v["added"] for v in j["views"]),
                                           "removed_px": sum(v["removed"] for v in j["views"])} if j else {})}
        if colored is not None:
            report["coloring"] = colored.info
        if out.get("poses") is not None:
            report["poses"] = out["poses"].to_dict()
        for row, a in zip(report["views"], agr.views):
            row["agreement"] = a
        dev = report.get("surface", {}).get("deviation")
        if dev is not None and agr.views and "raw_iou" in agr.views[0]:  # what finishing changed in the views
            change = [v["iou"] - v["raw_iou"] for v in agr.views]
            worst = int(np.argmax(np.abs(change)))
            report["surface"] = {**report["surface"], "deviation": {
                **dev, "worst_view_iou_change": round(float(change[worst]), 5), "worst_view": names[worst]}}
        report["agreement"] = {"limit": agr.limit, **figures.to_dict()}
        warnings = list(agr.warnings)
        lo, hi = self.roi(settings)
        disagreeing = []
        if warnings and roi_faces_touched(occupancy, lo, grid.voxel_size):  # the roi's cut: one warning (checks)
            disagreeing = [f"{names[i]} {agr.views[i]['disagreement_px']} px" for i in agr.worst if not agr.views[i]["ok"]]
            warnings = []
        suggested = self._angle_suggestions(grid, sils, cal, agr, names)
        if suggested:
            report["agreement"]["suggested_angles"] = suggested
            text = suggestion_text(suggested)
            if text and warnings:
                warnings[0] += f"; {text}"
        report.setdefault("warnings", []).extend(warnings)
        if getattr(s, "notes", ()):
            report["notes"] = list(s.notes)  # re-orthonormalised rotations
        # calibration images not used, and why (no board found, board moved)
        for what, fit in (("intrinsic", cal.intrinsics), ("turntable", cal.turntable)):
            if fit is not None:
                report["calibration"][f"{what}_rejected"] = dict(fit.rejected)
        if cal.turntable is not None:
            report["calibration"]["turntable_flagged"] = list(cal.turntable.flagged)
        report["warnings"].extend(cal.warnings())
        # a model too big: too few views, a narrow span, the roi's faces touched
        report["warnings"][:0] = model_warnings(cameras, occupancy, lo, hi, voxel_size=grid.voxel_size,
                                                tolerance=int(settings.tolerance), disagreeing=disagreeing)
        return ChecksStage(agr, figures, report)

    def _start_hull_masks(self, pool, raw, cameras, sils):
        """Queue :func:`hull_masks` on ``pool`` (a new one-thread pool when None) for :meth:`_made_hull_masks`."""
        pool = pool or ThreadPoolExecutor(1, thread_name_prefix="organlab-aaa")
        self._hull_job = (raw, cameras, sils, pool.submit(hull_masks, raw, cameras, sils))
        return pool

    def _made_hull_masks(self, raw, cameras, sils):
        """The hull masks made beside the finishing (:meth:`_run_surface`) when they are of this mesh, these
        cameras and these silhouettes; else None (the check makes them)."""
        job, self._hull_job = self._hull_job, None
        if job is None or job[0] is not raw or job[2] is not sils or len(job[1]) != len(cameras):
            return None
        if any(a is not b for a, b in zip(job[1], cameras)):
            return None
        try:
            return job[3].result()
        except Exception:  # noqa: BLE001 (made again by the check, which reports its error)
            return None

    def _angle_suggestions(self, grid, sils, cal, agr, names):
        """For a few flagged views whose poses come from their table angles: the angle each agrees best at."""
        views = [self.session.views[i] for i in self.views]
        bad = [i for i, v in enumerate(agr.views) if not v["ok"]]
        table = None if cal is None or cal.turntable is None else cal.turntable.camera
        if (not bad or table is None or len(bad) > MANY_FLAGGED * len(agr.views)
                or any(views[i].pose is not None for i in bad)):
            return {}
        return suggest_angles(table, [v.angle_deg for v in views], sils, bad, grid, names=names)

    def _reconstruction(self, settings, out):
        cal = out.get("calibration")
        carved, colored, surf, checks = out.get("carving"), out.get("coloring"), out.get("surface"), out.get("checks")
        occupancy = None if carved is None else (carved.occupancy if colored is None else colored.occupancy)
        return Reconstruction(
            self.session,
            None if carved is None else carved.grid,
            occupancy,
            None if surf is None else surf.mesh,
            [] if cal is None else _cameras(out),
            out.get("silhouettes") or [],
            None if checks is None else checks.report,
            None if carved is None else carved.field,
            None if colored is None else colored.colors,
            None if cal is None else cal.calibration,
            None if surf is None else surf.raw_mesh,
            None if surf is None else surf.aaa,
            settings=settings,
            agreement=None if checks is None else checks.figures,
            aaa_error=None if surf is None else surf.aaa_error,
            color_threshold=None if colored is None else colored.threshold,
            timings={k: self.timings[k] for k in STAGES if k in self.timings and k in out},
            views=list(self.views),
            coloring=None if colored is None else colored.info,
        )

    # ------------------------------------------------------------ for the viewer
    @property
    def is_aaa(self) -> bool:
        """Whether the session's specimen is an AAA (measured by default: ``Settings.measure=None``)."""
        return self.session is not None and bool(is_aaa_session(self.session))

    def view_silhouette(self, j: int, threshold: float | None = None) -> Silhouette:
        """The silhouette of the engine's view ``j`` at a threshold (its automatic one when None)."""
        return self.silhouette_model.silhouette(j, threshold=threshold)

    def stream_hull(self, settings: Settings, on_view: Callable[[int, Silhouette, Any, np.ndarray, VoxelGrid], None], *,
                    cancel: Callable[[], bool] | None = None) -> None:
        """Carve view by view (the thesis's test), calling ``on_view(j, silhouette, camera, occupancy, grid)``
        after each view: the hull so far, what the viewer shows at start-up and a capture shows as the table turns.

        The silhouettes and cameras are the engine's stages (kept for the next :meth:`run`).
        """
        settings = settings.validate()
        clock = _Clock(None, cancel)
        out = {"calibration": self._stage("calibration", settings, clock)}
        out["silhouettes"] = self._stage("silhouettes", settings, clock, out)
        grid = self.grid(settings)
        carver = ProgressiveCarver(grid, tolerance=settings.tolerance)
        for j, (sil, cam) in enumerate(zip(out["silhouettes"], out["calibration"].cameras)):
            on_view(j, sil, cam, carver.add_view(sil.mask, cam), grid)
            clock.check()

    def carving_views(self, rec: Reconstruction) -> np.ndarray:
        """For every voxel of ``rec``'s grid, the first view that carves it (-1: kept), ``grid.shape`` int16
        (:func:`organlab.carving.carving_views`)."""
        return carving_views(rec.masks, rec.cameras, rec.grid)

    def load_result(self, folder: str | Path) -> Reconstruction:
        """A result folder of this session (:meth:`Reconstruction.load`) with the engine's views, cameras and
        silhouettes (at the thresholds its report used), its agreement figures from the report, and the AAA
        measures (the report keeps only their summary: measured again from ``voxels.npz``, the volume
        ``organlab reconstruct`` measured)."""
        rec = Reconstruction.load(folder, session=self.session)
        rows = rec.report.get("views", [])
        rec.cameras = self.cameras()
        rec.silhouettes = [self.view_silhouette(j, rows[i].get("silhouette_threshold") if i < len(rows) else None)
                           for j, i in enumerate(self.views)]
        rec.views = list(self.views)
        if rec.agreement is not None and len(rows) == len(self.session.views):
            rec.agreement = rec.agreement.subset(self.views)
        if "aaa" in rec.report or self.is_aaa:
            try:
                rec.aaa = measure_aaa(rec.surface_volume(), rec.grid)
            except OrganlabError as e:
                rec.aaa_error = str(e)
        return rec


class LiveHull:
    """The hull carved view by view as views arrive: a capture, or a stream of views.

    The progressive form of the carving stage (the thesis's test,
    :class:`organlab.carving.ProgressiveCarver`); with a ``silhouette``
    function it also finds each arriving image's silhouette.

    Parameters
    ----------
    grid : VoxelGrid
    tolerance : int
        Views allowed to disagree before a voxel is carved.
    silhouette : callable(image) -> Silhouette, optional
        How an arriving image's silhouette is found (:meth:`add_image`).
    camera0 : Camera, optional
        The camera at table angle 0 (:meth:`for_capture`).

    Examples
    --------
    >>> from organlab.synthetic import Sphere, default_camera, render_masks
    >>> cams = [default_camera((160, 120)).at_table_angle(a) for a in (0, 90)]
    >>> hull = LiveHull(VoxelGrid.from_roi((-40, -40, 0), (40, 40, 80), 4.0))
    >>> for cam, cov in zip(cams, render_masks(Sphere(center=(0, 0, 40), radius=20), cams)):
    ...     occ = hull.add(cov >= 0.5, cam)
    >>> bool(occ.any()), hull.views
    (True, 2)
    """

    def __init__(self, grid: VoxelGrid, *, tolerance: int = 0, silhouette: Callable[[np.ndarray], Silhouette] | None = None,
                 camera0: Any = None):
        self.grid = grid
        self.camera0 = camera0
        self._carver = ProgressiveCarver(grid, tolerance=tolerance)
        self._silhouette = silhouette
        self.views = 0

    @property
    def occupancy(self) -> np.ndarray:
        """The hull so far, ``grid.shape`` bool."""
        return self._carver.occupancy

    def add(self, mask: np.ndarray, camera: Any) -> np.ndarray:
        """Carve with one more view's (H, W) bool mask; the hull so far."""
        self.views += 1
        return self._carver.add_view(mask, camera)

    def add_image(self, image: np.ndarray, camera: Any) -> tuple:
        """Find an arriving image's silhouette (when a ``silhouette`` function was given) and carve with it.

        Returns
        -------
        silhouette : Silhouette or None
        occupancy : (nx, ny, nz) bool or None
            None without a silhouette.
        """
        if self._silhouette is None:
            return None, None
        sil = self._silhouette(image)
        return sil, self.add(sil.mask, camera)

    @staticmethod
    def by_subtraction(background: np.ndarray, *, threshold: float | None = None, floor: float = 0.0,
                       noise: float = 0.0) -> Callable[[np.ndarray], Silhouette]:
        """The silhouette function of background subtraction against a model of the empty scene
        (:func:`organlab.silhouette.silhouette`; ``noise``, the frames' :func:`organlab.silhouette.background_noise`
        > 0: each view keeps its dim rim at the automatic threshold, as ``organlab reconstruct`` does)."""
        return lambda image: silhouette(image, background, threshold=threshold, floor=floor, noise=noise)

    @classmethod
    def for_capture(cls, session: Session | str | Path, *, voxel_size: float = 2.0, threshold: float | None = None,
                    tolerance: int = 0) -> LiveHull:
        """The live hull of a capture in progress, from what its session folder holds at the first view.

        The camera at table angle 0 from the turntable calibration
        (:func:`organlab.calibration.calibration_for`), the grid of the roi,
        and each image's silhouette as ``organlab reconstruct`` finds it
        (:class:`organlab.silhouette.SilhouetteModel`: background subtraction
        with the frames' noise floor, or keying against the session's
        ``backdrop``; a ``'border'`` backdrop is estimated from the image itself).

        Raises
        ------
        CalibrationError
            No turntable calibration to place the views.
        """
        s = session if isinstance(session, Session) else load_session(session)
        Settings(voxel_size=voxel_size, threshold=threshold, tolerance=tolerance).validate()
        cal, _ = calibration_for(s)
        if cal.turntable is None:
            raise CalibrationError(f"{s.json_path}: no turntable calibration to place the views "
                                   "(capture with the board on the table)")
        backdrop = getattr(s, "backdrop", None)
        needs_frames = backdrop is None or backdrop.get("color") == "frames"
        frames = [s.read(p, key=f"background_images[{k}]") for k, p in enumerate(s.background_images)]
        find = None
        if frames or not needs_frames:
            def find(image):
                model = SilhouetteModel([image], frames if needs_frames else None, backdrop=backdrop,
                                        names=[f"{s.json_path}: the captured view"])
                return model.silhouette(0, threshold=threshold)

        return cls(VoxelGrid.from_session(s, voxel_size), tolerance=tolerance, silhouette=find,
                   camera0=cal.turntable.camera)


#: Start the hull field beside the poses check (:meth:`Engine._start_field`).
SPECULATIVE_FIELD = True


class _FieldJob(NamedTuple):
    """A hull field started beside the poses check: its inputs and its future."""

    silhouettes: list
    cameras: list
    grid: VoxelGrid
    tolerance: int
    future: Any
    stop: Any  # threading.Event: set, the job stops after its next view

    def fits(self, sils, cameras, grid, tolerance):
        """Whether the carving's inputs are this job's (the same objects; the grid and tolerance equal)."""
        return (sils is self.silhouettes and len(cameras) == len(self.cameras)
                and all(a is b for a, b in zip(cameras, self.cameras)) and grid == self.grid
                and int(tolerance) == self.tolerance)


def _measure_beside(volume, grid):
    """:func:`measure_aaa` in the thread beside the finishing, its numba kernels on that thread alone (numba's
    thread count is per thread): a parallel kernel's second thread took the core the finishing was on."""
    import numba

    numba.set_num_threads(1)
    return measure_aaa(volume, grid)


def _cameras(out):
    """The views' cameras the stages after the silhouettes use: a ``poses`` stage's result (a refinement
    between the silhouettes and the carving, with a ``cameras`` attribute) when there is one, else the
    calibration's."""
    poses = out.get("poses")
    return out["calibration"].cameras if poses is None else poses.cameras


def _hashable(v):
    if isinstance(v, (list, tuple, np.ndarray)):
        return tuple(_hashable(x) for x in v)
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    return v


def _silhouette_info(s):
    """A view's report fields from its silhouette's ``info``: the keying's, and the joint step's change."""
    info = dict(getattr(s, "info", None) or {})
    joint = info.pop("joint", None)
    return {**({"silhouette_key": info} if info else {}), **({"silhouette_joint": joint} if joint else {})}


def _report(session, views, grid, occupancy, mesh, cameras, cal, how, sils, timings, settings):
    volume = grid.volume_of(occupancy)
    m = measure(mesh).to_dict()
    cam0 = cameras[0]
    camera = {"K": cam0.K.tolist(), "dist": cam0.dist.tolist(), "image_size": list(cam0.image_size)}
    if cal.rms_px is not None:
        camera["rms_px"] = cal.rms_px
    r = {
        "organlab_version": __version__,
        "session": session.name,
        "method": settings.method,
        "hull": settings.hull,
        "volume_mm3": volume,
        "mesh_volume_mm3": m["volume_mm3"],
        "mesh_area_mm2": m["area_mm2"],
        "watertight": m["watertight"],
        "voxel_size_mm": grid.voxel_size,
        "grid": {"origin_mm": list(grid.origin), "shape": list(grid.shape),
                 "occupied_voxels": int(np.count_nonzero(occupancy))},
        "timings_s": {k: round(v, 4) for k, v in timings.items()},
        "calibration": {"source": how, "rms_px": cal.rms_px, "turntable_rms_px": cal.turntable_rms_px},
        "views": [
            {"image": session.relpath(session.views[i].image), "angle_deg": session.views[i].angle_deg,
             "R": c.R.tolist(), "t": c.t.tolist(),
             "silhouette_threshold": s.threshold, "silhouette_source": s.source,
             **_silhouette_info(s)}
            for i, c, s in zip(views, cameras, sils)
        ],
        "camera": camera,
    }
    if cal.turntable_rms_px is not None:
        r["turntable_rms_px"] = cal.turntable_rms_px
    ref = session.reference.get("volume_mm3")
    if ref:
        r["reference"] = dict(session.reference)
        r["volume_error_pct"] = 100.0 * (volume - ref) / ref
        r["mesh_volume_error_pct"] = 100.0 * (m["volume_mm3"] - ref) / ref
    return r


def run(session: Session | str | Path, settings: Settings | None = None, *, calibration: Any = None,
        on_stage: Callable[[str, Any], None] | None = None, cancel: Callable[[], bool] | None = None,
        until: str | None = None, progress: Callable[[str], Any] | None = None) -> Reconstruction:
    """One run of every stage on a session: ``Engine(session, calibration=...).run(settings, ...)``.

    Examples
    --------
    >>> from organlab.engine import Settings, run
    >>> rec = run("sample_sessions/aaa_phantom", Settings(voxel_size=4.0, finish=False))
    >>> rec.report["watertight"], rec.agreement.mean_iou > 0.9
    (True, True)
    """
    return Engine(session, calibration=calibration).run(settings, on_stage=on_stage, cancel=cancel, until=until,
                                                        progress=progress)
