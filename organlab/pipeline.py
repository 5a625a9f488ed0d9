"""The whole pipeline: a session folder in, a measured mesh out.

:func:`reconstruct` chains the stage functions (calibration when needed,
silhouettes, carving, optional colouring, surface) and returns a
:class:`Reconstruction`; :func:`write_outputs` writes the files that
``session-format.md`` specifies.  The CLI only calls these two.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import __version__
from ._progress import NullProgress
from .camera import Camera
from .errors import SessionError
from .grid import VoxelGrid
from .session import Session, load_session, write_json

__all__ = ["Reconstruction", "session_cameras", "reconstruct", "write_outputs", "HULL_METHODS", "METHODS"]

HULL_METHODS = ("subvoxel", "thesis")
METHODS = ("hull", "coloring", "space_carving")


def _needs_calibration(session):
    have_intr = session.camera is not None or session.calibration is not None
    need_tt = any(v.pose is None for v in session.views)
    have_tt = bool(session.calibration and session.calibration.get("turntable"))
    return not have_intr or (need_tt and not have_tt)


def session_cameras(session, calibration=None):
    """The camera of every view of a session.

    Intrinsics come from ``session.json``'s ``camera`` when given, otherwise
    from the calibration; a view's pose is its given ``pose``, otherwise the
    turntable calibration's ``R_cam @ Rz(angle)``, ``t_cam``.

    Parameters
    ----------
    session : Session
    calibration : dict, optional
        Contents of ``calibration.json`` (default: the session's own).

    Returns
    -------
    list of Camera, one per view
    """
    calibration = calibration if calibration is not None else session.calibration
    intr = session.given_camera()
    if intr is None and calibration is not None:
        c = calibration["camera"]
        intr = Camera(c["K"], c["dist"], image_size=session.image_size)
    if intr is None:
        raise SessionError(f"{session.json_path}: camera: no intrinsics; run 'organlab calibrate {session.root}'")
    tt = (calibration or {}).get("turntable")
    cams = []
    for i, v in enumerate(session.views):
        if v.pose is not None:
            cams.append(intr.with_pose(*v.pose))
        elif tt is not None:
            cams.append(intr.with_pose(tt["R_cam"], tt["t_cam"]).at_table_angle(v.angle_deg))
        else:
            raise SessionError(
                f"{session.json_path}: views[{i}].pose: no pose and no turntable calibration; "
                f"run 'organlab calibrate {session.root}'"
            )
    return cams


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
    field : (nx, ny, nz) float32 or None
        Sub-voxel field whose 0.5 level is the surface (``hull='subvoxel'``).
    colors : (nx, ny, nz, 3) uint8 or None
        Voxel colours (``method='coloring'``).
    calibration : dict or None
        The calibration used (contents of ``calibration.json``), if any.
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
    calibration: dict | None = None


def reconstruct(
    session,
    *,
    voxel_size=1.0,
    threshold=None,
    method="hull",
    hull="subvoxel",
    color_threshold=None,
    tolerance=0,
    progress=None,
    max_memory=None,
):
    """Reconstruct a session: silhouettes, visual hull, (colouring), surface.

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
        Photo-consistency threshold (grey levels of standard deviation).
    tolerance : int
        Views allowed to disagree before a voxel is carved.
    progress : callable(stage) -> bar, optional
        Factory of per-stage progress bars (``bar(done, total)``, ``bar.close()``).
    max_memory : int, optional
        Bytes the voxel grid may take (estimated before any work); default the
        memory available now.  Larger grids are refused with the largest voxel
        size that fits (organlab.preflight).

    Returns
    -------
    Reconstruction
    """
    if not isinstance(session, Session):
        session = load_session(session)
    from .preflight import check_grid_memory, check_voxel_size, check_writable

    voxel_size = check_voxel_size(voxel_size)
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if hull not in HULL_METHODS:
        raise ValueError(f"hull must be one of {HULL_METHODS}, got {hull!r}")
    if threshold is not None and not (np.isfinite(threshold) and threshold > 0):
        raise SessionError(f"--threshold must be a finite number of grey levels > 0, got {threshold}")
    if color_threshold is not None and not (np.isfinite(color_threshold) and color_threshold > 0):
        raise SessionError(f"--color-threshold must be a finite number of grey levels > 0, got {color_threshold}")
    if not session.views:
        raise SessionError(f"{session.json_path}: views: the session has no views to reconstruct (calibration-only session)")
    check_grid_memory(session.roi_min, session.roi_max, voxel_size, max_memory=max_memory, method=method,
                      tolerance=tolerance if isinstance(tolerance, int) else 0, where=str(session.json_path))
    progress = progress or (lambda stage: NullProgress())
    timings = {}

    # --- calibration
    calibration = session.calibration
    if _needs_calibration(session):
        from . import calibration as calib

        check_writable(session.root, what="calibration.json")
        bar = progress("calibration")
        t0 = time.perf_counter()
        calibration = calib.calibrate_session(session, progress=bar)
        try:
            calib.write_calibration(session, calibration)
        except OSError as e:
            raise SessionError(f"{session.calibration_path}: cannot write the calibration ({e.strerror or e}); "
                               f"run 'organlab reconstruct' on a writable copy of the session") from None
        timings["calibration"] = time.perf_counter() - t0
        bar.close()
    cameras = session_cameras(session, calibration)

    # --- silhouettes
    from .silhouette import session_silhouettes

    bar = progress("silhouettes")
    t0 = time.perf_counter()
    # read once: colouring needs the same images
    images = [session.read(v.image, key=f"views[{i}].image") for i, v in enumerate(session.views)]
    sils = session_silhouettes(session, images=images, threshold=threshold, progress=bar)
    timings["silhouettes"] = time.perf_counter() - t0
    bar.close()

    # --- carving
    from . import carving

    grid = VoxelGrid.from_roi(session.roi_min, session.roi_max, voxel_size)
    bar = progress("carving")
    t0 = time.perf_counter()
    field_ = None
    if hull == "thesis":
        occupancy = carving.carve([s.mask for s in sils], cameras, grid, tolerance=tolerance)
    else:
        field_ = carving.hull_field([s.coverage for s in sils], cameras, grid, tolerance=tolerance, progress=bar)
        occupancy = field_ >= 0.5
    bar(len(cameras), len(cameras))
    timings["carving"] = time.perf_counter() - t0
    bar.close()
    if not occupancy.any():
        raise SessionError(
            f"{session.json_path}: carving left no voxel: the silhouettes do not agree with the cameras "
            "(check the calibration, the roi and the threshold)"
        )

    # --- colouring
    colors = None
    if method != "hull":
        from . import coloring

        bar = progress("coloring")
        t0 = time.perf_counter()
        kw = {} if color_threshold is None else {"threshold": color_threshold}
        kind = "voxel_coloring" if method == "coloring" else "space_carving"
        res = coloring.color_voxels(
            images, cameras, occupancy, grid, method=kind, masks=[s.mask for s in sils], progress=bar, **kw
        )
        occupancy, colors, colored = res.occupancy, res.colors, res.colored
        timings["coloring"] = time.perf_counter() - t0
        bar.close()

    # --- surface
    from .surface import Mesh, mesh_from_volume

    bar = progress("surface")
    t0 = time.perf_counter()
    # after colouring, the surface is the coloured voxel model's: the hull field knows
    # nothing of the voxels colouring carved, and setting them outside in the field
    # moved the surface inward by up to a voxel wherever colouring carved a surface voxel
    surface_of = occupancy if (colors is not None or field_ is None) else field_
    mesh = mesh_from_volume(surface_of, grid, level=0.5)
    if colors is not None:
        mesh = Mesh(mesh.vertices, mesh.faces, _vertex_colors(mesh.vertices, colored, colors, grid))
    bar(1, 1)
    timings["surface"] = time.perf_counter() - t0
    bar.close()

    report = _report(session, grid, occupancy, mesh, cameras, calibration, sils, timings, method, hull)
    _add_agreement(report, session, grid, mesh, cameras, sils)
    return Reconstruction(session, grid, occupancy, mesh, cameras, sils, report, field_, colors, calibration)


def _add_agreement(report, session, grid, mesh, cameras, sils):
    """View agreement (organlab.agreement) into the report: per view, worst views, warnings."""
    from .agreement import view_agreement

    names = [session.relpath(v.image) for v in session.views]
    agr = view_agreement(mesh, cameras, sils, voxel_size=grid.voxel_size, names=names)
    for row, a in zip(report["views"], agr.views):
        row["agreement"] = a
    report["agreement"] = {"limit": agr.limit, "worst_views": [names[i] for i in agr.worst[:3]]}
    report.setdefault("warnings", []).extend(agr.warnings)
    if getattr(session, "notes", ()):
        report["notes"] = list(session.notes)  # what loading corrected (re-orthonormalised rotations)


def _vertex_colors(vertices, colored, colors, grid):
    """Colour of the nearest coloured voxel of each vertex."""
    from scipy import ndimage

    has = np.asarray(colored, dtype=bool)
    if not has.any():
        return np.full((len(vertices), 3), 128, np.uint8)
    _, idx = ndimage.distance_transform_edt(~has, return_indices=True)
    ijk = np.rint((vertices - np.asarray(grid.origin)) / grid.voxel_size).astype(int)
    ijk = np.clip(ijk, 0, np.asarray(grid.shape) - 1)
    src = idx[:, ijk[:, 0], ijk[:, 1], ijk[:, 2]]
    return colors[src[0], src[1], src[2]]


def _report(session, grid, occupancy, mesh, cameras, calibration, sils, timings, method, hull):
    volume = grid.volume_of(occupancy)
    cam0 = cameras[0]
    camera = {"K": cam0.K.tolist(), "dist": cam0.dist.tolist(), "image_size": list(cam0.image_size)}
    if session.camera is None and calibration is not None and "rms_px" in calibration.get("camera", {}):
        camera["rms_px"] = calibration["camera"]["rms_px"]
    r = {
        "organlab_version": __version__,
        "session": session.name,
        "method": method,
        "hull": hull,
        "volume_mm3": volume,
        "mesh_volume_mm3": mesh.volume,
        "mesh_area_mm2": mesh.area,
        "watertight": bool(mesh.is_watertight),
        "voxel_size_mm": grid.voxel_size,
        "grid": {"origin_mm": list(grid.origin), "shape": list(grid.shape), "occupied_voxels": int(occupancy.sum())},
        "timings_s": {k: round(v, 4) for k, v in timings.items()},
        "views": [
            {"image": session.relpath(v.image), "angle_deg": v.angle_deg, "R": c.R.tolist(), "t": c.t.tolist(),
             "silhouette_threshold": s.threshold, "silhouette_source": s.source}
            for v, c, s in zip(session.views, cameras, sils)
        ],
        "camera": camera,
    }
    if calibration is not None and calibration.get("turntable") and "rms_px" in calibration["turntable"]:
        r["turntable_rms_px"] = calibration["turntable"]["rms_px"]
    ref = session.reference.get("volume_mm3")
    if ref:
        r["reference"] = dict(session.reference)
        r["volume_error_pct"] = 100.0 * (volume - ref) / ref
        r["mesh_volume_error_pct"] = 100.0 * (mesh.volume - ref) / ref
    return r


def write_outputs(rec, out_dir, *, atomic=True):
    """Write ``report.json``, ``voxels.npz``, ``mesh.ply`` and ``mesh.stl``.

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
    if rec.field is not None:
        arrays["field"] = rec.field
    np.savez_compressed(paths["voxels"], **arrays)
    write_ply(paths["ply"], rec.mesh)
    write_stl(paths["stl"], rec.mesh)
    write_json(paths["report"], rec.report)
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
