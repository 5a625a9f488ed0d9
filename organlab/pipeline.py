"""The whole pipeline: a session folder in, a measured mesh out.

:func:`reconstruct` is one run of :class:`organlab.engine.Engine`, the stage
functions in sequence (what a notebook writes by hand), plus progress bars
and timings::

    cal, how = calibration_for(session)        # organlab.calibration
    cameras = cal.cameras(session)
    sils = silhouettes(session)                # organlab.silhouette
    cameras = refine_poses(session, cal, sils, cameras=cameras).cameras  # organlab.poses
    grid = VoxelGrid.from_session(session, voxel_size=1.0)
    field = hull_field(sils, cameras, grid, sparse=True)  # organlab.carving
    mesh = mesh_from_field(field, grid)        # organlab.surface
    mesh = finish_surface(mesh, voxel_size=1.0).mesh
    measure(mesh)

:func:`write_outputs` writes the files that ``docs/session-format.md``
specifies (:meth:`Reconstruction.save`).  The CLI only calls these two.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from .calibration import calibration_for
from .engine import HULL_METHODS, METHODS, AgreementFigures, Engine, Reconstruction, Settings, pixel_footprint
from .session import Session, load_session

__all__ = ["Reconstruction", "Settings", "session_cameras", "reconstruct", "write_outputs", "summary_table",
           "pixel_footprint", "HULL_METHODS", "METHODS"]


def session_cameras(session: Session | str | Path, calibration: Any = None) -> list:
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
    if not isinstance(session, Session):
        session = load_session(session)
    return calibration_for(session, calibration=calibration)[0].cameras(session)


def reconstruct(
    session: Session | str | Path,
    *,
    voxel_size: float = 1.0,
    threshold: float | None = None,
    method: str = "hull",
    hull: str = "subvoxel",
    color_threshold: float | None = None,
    tolerance: int = 0,
    calibration: Any = None,
    recalibrate: bool = False,
    progress: Callable[[str], Any] | None = None,
    max_memory: int | None = None,
    finish: bool = True,
    measure: bool | None = None,
    refine_poses: str = "auto",
    joint_silhouettes: str = "auto",
) -> Reconstruction:
    """Reconstruct a session: calibration (when needed), silhouettes, visual hull, (colouring), surface.

    Nothing is written, into the session or elsewhere: see :func:`write_outputs`.
    One run of :class:`organlab.engine.Engine` with these :class:`organlab.engine.Settings`.

    Parameters
    ----------
    session : Session or str or Path
        A loaded session or its folder.
    voxel_size : float, mm
    threshold : float, optional
        Silhouette threshold in grey levels (automatic per view when omitted).
    method : {'hull', 'coloring', 'space_carving', 'photo'}
        ``'photo'``: patch NCC between neighbouring views, carving free space
        in front of matched depths (:func:`organlab.coloring.photo_carve`;
        ``color_threshold`` is then its NCC gain).
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
    joint_silhouettes : {'auto', 'on', 'off'}
        Segment every view again with the hull of all the views as a prior
        (:meth:`organlab.silhouette.SilhouetteModel.joint`); ``'auto'``: see
        :class:`organlab.engine.Settings`.

    Returns
    -------
    Reconstruction

    Raises
    ------
    organlab.engine.SettingsError
        A setting out of range, named as the parameter above.

    Examples
    --------
    >>> import tempfile
    >>> import organlab as ol
    >>> from organlab.synthetic import with_true_cameras
    >>> s = ol.load_session(with_true_cameras("sample_sessions/aaa_phantom", tempfile.mkdtemp() + "/aaa", step=6))
    >>> rec = ol.reconstruct(s, voxel_size=4.0)  # calibration, silhouettes, hull, surface, checks
    >>> rec.mesh.is_watertight, round(rec.report["mesh_volume_mm3"], -3)  # the phantom: 165 661 mm^3 (6 views)
    (True, 173000.0)
    """
    settings = Settings(voxel_size=voxel_size, threshold=threshold, method=method, hull=hull,
                        color_threshold=color_threshold, tolerance=tolerance, finish=finish, measure=measure,
                        refine_poses=refine_poses, joint_silhouettes=joint_silhouettes)
    settings.validate()  # before the session is read
    engine = Engine(session, calibration=calibration, recalibrate=recalibrate, max_memory=max_memory)
    return engine.run(settings, progress=progress)


def write_outputs(rec: Reconstruction, out_dir: str | Path, *, atomic: bool = True) -> dict:
    """Write ``report.json``, ``voxels.npz``, ``mesh.ply``, ``mesh.stl`` (and ``calibration.json``).

    :meth:`Reconstruction.save`.  ``calibration.json`` is the calibration
    used, when it was fitted from board images (not when ``session.json``
    gave the camera and every pose).

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
    return rec.save(out_dir, atomic=atomic)


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
    figures = AgreementFigures.from_report(report)
    if figures is not None:  # the figures and the ranking the viewer shows (organlab.engine.AgreementFigures)
        rows.append(("agreement", f"mean IoU {figures.mean_iou:.3f} over {len(figures.iou)} views"))
        rows.append(("worst views", ", ".join(f"{figures.names[i]} ({100 * figures.disagreement[i]:.2f} % unexplained, "
                                              f"IoU {figures.iou[i]:.3f})" for i in figures.ranking[:2])))
    for k, v in report["timings_s"].items():
        rows.append((f"time {k}", f"{v:.2f} s"))
    w = max(len(k) for k, _ in rows)
    return "\n".join(f"  {k:<{w}}  {v}" for k, v in rows)
