"""The whole pipeline: a session folder in, a measured mesh out.

:func:`reconstruct` is exactly the stage functions in sequence (what a notebook
writes by hand), plus progress bars and timings::

    cal, how = calibration_for(session)        # organlab.calibration
    cameras = cal.cameras(session)
    sils = silhouettes(session)                # organlab.silhouette
    cameras = refine_poses(session, cal, sils, cameras=cameras).cameras  # organlab.poses
    grid = VoxelGrid.from_session(session, voxel_size=1.0)
    field = hull_field(sils, cameras, grid, sparse=True)  # organlab.carving
    mesh = mesh_from_field(field, grid)        # organlab.surface
    mesh, steps = finish_surface(mesh, voxel_size=1.0)
    measure(mesh)

:func:`write_outputs` writes the files that ``docs/session-format.md``
specifies.  The CLI only calls these two.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import __version__
from ._progress import NullProgress
from .errors import SessionError
from .grid import VoxelGrid
from .poses import refine_poses as _refine_poses
from .session import Session, load_session, write_json

__all__ = ["Reconstruction", "session_cameras", "reconstruct", "write_outputs", "summary_table", "HULL_METHODS", "METHODS"]

HULL_METHODS = ("subvoxel", "thesis")
METHODS = ("hull", "coloring", "space_carving")


def session_cameras(session, calibration=None):
    """The camera of every view of a session.

    Parameters
    ----------
    session : Session or str or Path
    calibration : Calibration or str or Path, optional
        Default: the session's own (given in ``session.json``, its matching
        ``calibration.json``, or computed now from its board images: see
        :func:`organlab.calibration.calibration_for`).

    Returns
    -------
    list of Camera, one per view
    """
    from .calibration import calibration_for

    if not isinstance(session, Session):
        session = load_session(session)
    return calibration_for(session, calibration=calibration)[0].cameras(session)


@dataclass
class Reconstruction:
    """Everything :func:`reconstruct` computed.

    Attributes
    ----------
    session : Session
    grid : VoxelGrid
    occupancy : (nx, ny, nz) bool
        The carved voxel model.
    mesh : organlab.surface.Mesh
    cameras : list of Camera
    silhouettes : list of organlab.silhouette.Silhouette
    report : dict
        The content of ``report.json``.
    field : organlab.carving.BandField or None
        Sub-voxel field whose 0.5 level is the surface (``hull='subvoxel'``),
        stored in a narrow band; ``np.asarray(field)`` is the dense
        ``(nx, ny, nz)`` float32 field.
    colors : (nx, ny, nz, 3) uint8 or None
        Voxel colours (``method='coloring'``).
    calibration : organlab.calibration.Calibration
        The calibration used.
    """

    session: Session
    grid: VoxelGrid
    occupancy: np.ndarray
    mesh: object
    cameras: list
    silhouettes: list
    report: dict
    field: np.ndarray | None = None
    colors: np.ndarray | None = None
    calibration: object = None
    raw_mesh: object = None  # the marching-cubes mesh before organlab.surface.finish_surface
    aaa: object = None  # organlab.surface.AAAMeasures when measured


class _Stages:
    """Per-stage progress bars and timings."""

    def __init__(self, progress):
        self.progress = progress or (lambda stage: NullProgress())
        self.timings = {}

    def run(self, name, fn, *args, **kwargs):
        """``fn(*args, progress=bar, **kwargs)``, timed as stage ``name``."""
        bar = self.progress(name)
        t0 = time.perf_counter()
        out = fn(*args, progress=bar, **kwargs)
        self.timings[name] = time.perf_counter() - t0
        bar.close()
        return out


def _check_options(session, voxel_size, threshold, method, hull):
    from .preflight import check_voxel_size

    check_voxel_size(voxel_size)  # finite and > 0
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if hull not in HULL_METHODS:
        raise ValueError(f"hull must be one of {HULL_METHODS}, got {hull!r}")
    if threshold is not None and not (np.isfinite(threshold) and threshold > 0):
        raise SessionError(f"--threshold must be a finite number of grey levels > 0, got {threshold}")
    if not session.views:
        raise SessionError(f"{session.json_path}: views: the session has no views to reconstruct (calibration-only session)")


def _calibration_stage(stages, session, calibration, recalibrate):
    """The calibration to use; timed (and a bar shown) only when one is computed."""
    from .calibration import calibration_for

    bar = None

    def progress(done, total):
        nonlocal bar
        bar = bar or stages.progress("calibration")
        bar(done, total)

    t0 = time.perf_counter()
    cal, how = calibration_for(session, calibration=calibration, recalibrate=recalibrate, progress=progress)
    if how == "computed" or how.startswith("recomputed"):
        stages.timings["calibration"] = time.perf_counter() - t0
    if bar is not None:
        bar.close()
    return cal, how


def _carve(sils, cameras, grid, *, hull, tolerance, progress):
    from .carving import carve, hull_field

    if hull == "thesis":
        occupancy, field = carve(sils, cameras, grid, tolerance=tolerance), None
    else:  # the field in a narrow band about the surface: cost grows with the surface, not the volume
        field = hull_field(sils, cameras, grid, tolerance=tolerance, progress=progress, sparse=True)
        occupancy = field.occupancy()
    progress(len(cameras), len(cameras))
    return occupancy, field


def _surface(session, occupancy, field, colors, colored, grid, *, finish, measure, progress, cameras=None):
    """Marching cubes (raw mesh), then the finished surface and the AAA measures (:func:`_finish_and_measure`)."""
    from .surface import color_vertices, mesh_from_field

    # after colouring, the surface is the coloured voxel model's: the hull field knows
    # nothing of the voxels colouring carved, and setting them outside in the field
    # moved the surface inward by up to a voxel wherever colouring carved a surface voxel
    surface_of = occupancy if (colors is not None or field is None) else field
    raw = mesh_from_field(surface_of, grid)
    if colors is not None:
        raw = color_vertices(raw, colors, colored, grid)
    footprint = None if not cameras else pixel_footprint(cameras, grid)
    mesh, aaa, extra = _finish_and_measure(session, raw, surface_of, grid, finish, measure, footprint)
    progress(1, 1)
    return raw, mesh, aaa, extra


def reconstruct(
    session,
    *,
    voxel_size=1.0,
    threshold=None,
    method="hull",
    hull="subvoxel",
    color_threshold=None,
    tolerance=0,
    calibration=None,
    recalibrate=False,
    progress=None,
    max_memory=None,
    finish=True,
    measure=None,
    refine_poses="auto",
):
    """Reconstruct a session: calibration (when needed), silhouettes, visual hull, (colouring), surface.

    Nothing is written, into the session or elsewhere: see :func:`write_outputs`.

    Parameters
    ----------
    session : Session or str or Path
        A loaded session or its folder.
    voxel_size : float, mm
    threshold : float, optional
        Silhouette threshold in grey levels (automatic per view when omitted).
    method : {'hull', 'coloring', 'space_carving'}
        ``'coloring'`` runs Seitz & Dyer's layered voxel colouring on the hull
        (cameras must all lie above the specimen, or on one side of it: the
        ordinal visibility constraint, checked); ``'space_carving'`` the
        general method with exact visibility for any camera layout.
    hull : {'subvoxel', 'thesis'}
        ``'thesis'``: the thesis's test, a voxel is kept when the bounding
        box of its 8 projected corners touches the silhouette in every view
        (never misses the specimen, inflates thin parts); the mesh is the
        occupancy's surface.  ``'subvoxel'``: the hull field of sub-pixel
        silhouettes; occupancy = voxel centres inside the hull, mesh = the
        field's 0.5 level, between voxel centres.
    color_threshold : float, optional
        Photo-consistency threshold (grey levels: spread of the view colours
        about a shading curve of the table angle); automatic when omitted
        (:data:`organlab.coloring.PIPELINE_OPTIONS`: exposure normalised,
        silhouette guard on).
    tolerance : int
        Views allowed to disagree before a voxel is carved.
    calibration : Calibration or str or Path, optional
        Use this calibration (checked against the session) instead of the
        session's own; see :func:`organlab.calibration.calibration_for`.
    recalibrate : bool
        Calibrate from the board images even when the session's
        ``calibration.json`` matches it.
    progress : callable(stage) -> bar, optional
        Factory of per-stage progress bars (``bar(done, total)``, ``bar.close()``).
    max_memory : int, optional
        Bytes the voxel grid may take (estimated before any work); default the
        memory available now.  Larger grids are refused with the largest voxel
        size that fits (organlab.preflight).
    finish : bool
        Repair, smooth and remesh the marching-cubes surface
        (:func:`organlab.surface.finish_surface`: watertight, manifold, no slivers).
    measure : bool, optional
        AAA measurements (:func:`organlab.surface.measure_aaa`); default: when
        the session says its specimen is an AAA.
    refine_poses : {'auto', 'on', 'off'}
        Correct the poses from the silhouettes (:func:`organlab.poses.refine_poses`),
        kept only when the leave-out gate accepts; ``'auto'``: when views disagree.

    Returns
    -------
    Reconstruction
    """
    from .silhouette import silhouettes

    if not isinstance(session, Session):
        session = load_session(session)
    _check_options(session, voxel_size, threshold, method, hull)
    if refine_poses not in ("auto", "on", "off"):
        raise ValueError(f"refine_poses must be 'auto', 'on' or 'off', got {refine_poses!r}")
    stages = _Stages(progress)

    _preflight(session, voxel_size, color_threshold, method, tolerance, max_memory)
    cal, how = _calibration_stage(stages, session, calibration, recalibrate)
    cameras = cal.cameras(session)
    images = session.images()  # read once: colouring needs the same images
    sils = stages.run("silhouettes", silhouettes, session, images=images, threshold=threshold)
    poses = _refine_poses(session, cal, sils, mode=refine_poses, cameras=cameras, names=[session.relpath(v.image) for v in session.views])
    cameras = poses.cameras  # its time is in report["poses"]["seconds"]
    grid = VoxelGrid.from_session(session, voxel_size)
    occupancy, field = stages.run("carving", _carve, sils, cameras, grid, hull=hull, tolerance=tolerance)
    if not occupancy.any():
        raise SessionError(
            f"{session.json_path}: carving left no voxel: the silhouettes do not agree with the cameras "
            "(check the calibration, the roi and the threshold)"
        )
    colors = colored = coloring_info = None
    if method != "hull":
        from .coloring import report_entry

        res = stages.run("coloring", _color, images, cameras, occupancy, grid, sils, method, color_threshold)
        coloring_info = report_entry(res, occupancy, grid)
        occupancy, colors, colored = res.occupancy, res.colors, res.colored
    raw_mesh, mesh, aaa, extra = stages.run("surface", _surface, session, occupancy, field, colors, colored, grid,
                                            finish=finish, measure=measure, cameras=cameras)
    report = _report(session, grid, occupancy, mesh, cameras, cal, how, sils, stages.timings, method, hull)
    report.update(extra)
    report["poses"] = poses.to_dict()
    if coloring_info is not None:
        report["coloring"] = coloring_info
    _add_checks(report, session, grid, mesh, cameras, sils, cal)
    return Reconstruction(session, grid, occupancy, mesh, cameras, sils, report, field, colors, cal, raw_mesh, aaa)


def pixel_footprint(cameras, grid):
    """Median size of a pixel at the centre of the voxel space over the views, mm.

    What the silhouettes resolve at the specimen: the finished surface's edges
    need not be shorter (``finish_surface(min_edge_mm=...)``).
    """
    lo, hi = grid.bounds
    c = (np.asarray(lo, float) + np.asarray(hi, float)) / 2
    return float(np.median([cam.pixel_footprint(c) for cam in cameras]))


def _finish_and_measure(session, mesh, volume, grid, finish, measure, footprint=None):
    """The finished surface (issue 9) and, for an AAA session or when asked, the AAA measures.

    ``footprint``: a pixel's size at the specimen, mm (:func:`pixel_footprint`), the
    remeshing's shortest automatic edge (default ``finish_surface``'s).
    Returns the surface, the measures (or None) and the report's extra keys.
    """
    from .errors import OrganlabError
    from .surface import finish_surface, is_aaa_session, measure_aaa

    extra, aaa = {"raw_mesh_volume_mm3": mesh.volume}, None
    if finish:
        kw = {} if footprint is None else {"min_edge_mm": footprint}
        mesh, extra["surface"] = finish_surface(mesh, voxel_size=grid.voxel_size, **kw)
        if footprint is not None:
            extra["surface"]["pixel_footprint_mm"] = footprint
    if measure or (measure is None and is_aaa_session(session)):
        try:
            aaa = measure_aaa(volume, grid)
            extra["aaa"] = aaa.summary()
        except OrganlabError as e:
            if measure:  # asked for: an error; automatic: noted in the report
                raise
            extra["aaa_error"] = str(e)
    return mesh, aaa, extra


def _preflight(session, voxel_size, color_threshold, method, tolerance, max_memory):
    """Before the long work: the grid's memory (organlab.preflight), a finite colour threshold."""
    from .preflight import check_grid_memory

    if color_threshold is not None and not (np.isfinite(color_threshold) and color_threshold > 0):
        raise SessionError(f"--color-threshold must be a finite number of grey levels > 0, got {color_threshold}")
    check_grid_memory(session.roi_min, session.roi_max, voxel_size, max_memory=max_memory, method=method,
                      tolerance=tolerance if isinstance(tolerance, int) else 0, where=str(session.json_path))


def _angle_suggestions(session, grid, sils, cal, agr, names):
    """For a few flagged views whose poses come from their table angles: the angle each agrees best at."""
    from .agreement import _MANY, suggest_angles

    bad = [i for i, v in enumerate(agr.views) if not v["ok"]]
    table = None if cal is None or cal.turntable is None else cal.turntable.camera
    if not bad or table is None or len(bad) > _MANY * len(agr.views) or any(session.views[i].pose is not None for i in bad):
        return {}
    return suggest_angles(table, [v.angle_deg for v in session.views], sils, bad, grid, names=names)


def _add_checks(report, session, grid, mesh, cameras, sils, cal):
    """Trust checks into the report (issue 15): view agreement, what loading corrected."""
    from .agreement import suggestion_text, view_agreement

    names = [session.relpath(v.image) for v in session.views]
    agr = view_agreement(mesh, cameras, sils, voxel_size=grid.voxel_size, names=names)
    for row, a in zip(report["views"], agr.views):
        row["agreement"] = a
    report["agreement"] = {"limit": agr.limit, "worst_views": [names[i] for i in agr.worst[:3]]}
    warnings = list(agr.warnings)
    suggested = _angle_suggestions(session, grid, sils, cal, agr, names)
    if suggested:
        report["agreement"]["suggested_angles"] = suggested
        text = suggestion_text(suggested)
        if text and warnings:
            warnings[0] += f"; {text}"
    report.setdefault("warnings", []).extend(warnings)
    if getattr(session, "notes", ()):
        report["notes"] = list(session.notes)  # re-orthonormalised rotations
    # calibration images not used, and why (no board found, board moved)
    for what, fit in (("intrinsic", cal.intrinsics), ("turntable", cal.turntable)):
        if fit is not None:
            report["calibration"][f"{what}_rejected"] = dict(fit.rejected)
    if cal.turntable is not None:
        report["calibration"]["turntable_flagged"] = list(cal.turntable.flagged)
    report["warnings"].extend(cal.warnings())


def _color(images, cameras, occupancy, grid, sils, method, color_threshold, *, progress):
    from .coloring import PIPELINE_OPTIONS, color_voxels

    kind = "voxel_coloring" if method == "coloring" else "space_carving"
    return color_voxels(images, cameras, occupancy, grid, method=kind, masks=[s.mask for s in sils], progress=progress,
                        threshold="auto" if color_threshold is None else color_threshold, **PIPELINE_OPTIONS)



def _report(session, grid, occupancy, mesh, cameras, cal, how, sils, timings, method, hull):
    from .surface import measure

    volume = grid.volume_of(occupancy)
    m = measure(mesh)
    cam0 = cameras[0]
    camera = {"K": cam0.K.tolist(), "dist": cam0.dist.tolist(), "image_size": list(cam0.image_size)}
    if cal.rms_px is not None:
        camera["rms_px"] = cal.rms_px
    r = {
        "organlab_version": __version__,
        "session": session.name,
        "method": method,
        "hull": hull,
        "volume_mm3": volume,
        "mesh_volume_mm3": m["volume_mm3"],
        "mesh_area_mm2": m["area_mm2"],
        "watertight": m["watertight"],
        "voxel_size_mm": grid.voxel_size,
        "grid": {"origin_mm": list(grid.origin), "shape": list(grid.shape), "occupied_voxels": int(occupancy.sum())},
        "timings_s": {k: round(v, 4) for k, v in timings.items()},
        "calibration": {"source": how, "rms_px": cal.rms_px, "turntable_rms_px": cal.turntable_rms_px},
        "views": [
            {"image": session.relpath(v.image), "angle_deg": v.angle_deg, "R": c.R.tolist(), "t": c.t.tolist(),
             "silhouette_threshold": s.threshold, "silhouette_source": s.source,
             **({"silhouette_key": s.info} if getattr(s, "info", None) else {})}
            for v, c, s in zip(session.views, cameras, sils)
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


def write_outputs(rec, out_dir, *, atomic=True):
    """Write ``report.json``, ``voxels.npz``, ``mesh.ply``, ``mesh.stl`` (and ``calibration.json``).

    ``calibration.json`` is the calibration used, when it was fitted from
    board images (not when ``session.json`` gave the camera and every pose).

    Parameters
    ----------
    rec : Reconstruction
    out_dir : str or Path
        Created when missing.
    atomic : bool
        Write into a temporary folder beside ``out_dir`` and replace
        ``out_dir`` with it only when every file is written
        (:func:`organlab.preflight.atomic_output_dir`): an interrupted run
        leaves the previous result intact, and no file of an earlier run
        stays mixed with the new ones.  ``False`` writes into ``out_dir``
        directly (for a caller that manages its own temporary folder).

    Returns
    -------
    dict of str -> Path
    """
    if atomic:
        from .preflight import atomic_output_dir

        with atomic_output_dir(out_dir) as tmp:
            paths = write_outputs(rec, tmp, atomic=False)
        return {k: Path(out_dir) / p.name for k, p in paths.items()}
    from .carving import BandField
    from .surface import write_ply, write_stl

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {k: out / n for k, n in (("report", "report.json"), ("voxels", "voxels.npz"), ("ply", "mesh.ply"), ("stl", "mesh.stl"))}
    arrays = {
        "occupancy": np.ascontiguousarray(rec.occupancy, dtype=bool),
        "origin_mm": np.asarray(rec.grid.origin, dtype=np.float64),
        "voxel_size_mm": np.float64(rec.grid.voxel_size),
    }
    if rec.colors is not None:
        arrays["colors"] = rec.colors
    if isinstance(rec.field, BandField):  # the band only: the file grows with the surface, not the volume
        arrays.update(rec.field.to_arrays(prefix="field_"))
    elif rec.field is not None:  # a dense field (hull_field(sparse=False)) as earlier versions stored it
        arrays["field"] = np.asarray(rec.field, dtype=np.float32)
    np.savez_compressed(paths["voxels"], **arrays)
    write_ply(paths["ply"], rec.mesh)
    write_stl(paths["stl"], rec.mesh)
    write_json(paths["report"], rec.report)
    cal = rec.calibration
    if cal is not None and (cal.intrinsics is not None or cal.turntable is not None):
        paths["calibration"] = cal.save(out / "calibration.json")
    return paths


def summary_table(report):
    """A short plain-text summary of a report (the CLI prints it)."""
    rows = [("voxel size", f"{report['voxel_size_mm']:g} mm")]
    ref = report.get("reference", {}).get("volume_mm3")
    rows.append(("voxel volume", f"{report['volume_mm3'] / 1000:.2f} cm3" + (f"  ({report['volume_error_pct']:+.2f} % vs reference)" if ref else "")))
    rows.append(("mesh volume", f"{report['mesh_volume_mm3'] / 1000:.2f} cm3" + (f"  ({report['mesh_volume_error_pct']:+.2f} % vs reference)" if ref else "")))
    if ref:
        rows.append(("reference", f"{ref / 1000:.2f} cm3"))
    rows.append(("mesh area", f"{report['mesh_area_mm2'] / 100:.2f} cm2"))
    rows.append(("watertight", "yes" if report["watertight"] else "NO"))
    if "surface" in report:
        q = report["surface"]["final"]
        text = f"{q['faces']} faces, smallest angle {q['min_angle_deg']:.1f} deg (repaired, remeshed)"
        if q.get("faces_below_20deg"):  # slivers left by the remeshing (seen below 1 mm voxels: docs/surfaces.md)
            text += f"; {q['faces_below_20deg']} faces below 20 deg"
        rows.append(("surface", text))
    if "aaa" in report:
        a = report["aaa"]
        rows.append(("AAA max diameter", f"{a['max_diameter_mm']:.1f} mm at z {a['max_location_mm'][2]:.1f} mm, "
                     f"sac {a['sac_length_mm']:.0f} mm"))
    if report.get("poses"):
        rows.append(("poses", report["poses"]["reason"]))
    source = report.get("calibration", {}).get("source")
    if source:
        rows.append(("calibration", source))
    if "rms_px" in report["camera"]:
        rows.append(("calib. RMS", f"{report['camera']['rms_px']:.3f} px"))
    if "turntable_rms_px" in report:
        rows.append(("turntable RMS", f"{report['turntable_rms_px']:.3f} px"))
    if report.get("agreement"):
        worst = [(r["image"], r["agreement"]) for r in report["views"] if r["image"] in report["agreement"]["worst_views"]]
        worst.sort(key=lambda x: -x[1]["disagreement"])
        rows.append(("worst views", ", ".join(f"{n} (IoU {a['iou']:.3f}, {100 * a['disagreement']:.2f} % unexplained)" for n, a in worst[:2])))
    for k, v in report["timings_s"].items():
        rows.append((f"time {k}", f"{v:.2f} s"))
    w = max(len(k) for k, _ in rows)
    return "\n".join(f"  {k:<{w}}  {v}" for k, v in rows)
