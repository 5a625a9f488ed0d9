"""The ``organlab mesh`` steps on a result folder, and the AAA picture.

:func:`mesh_result` reads ``voxels.npz`` written by
:func:`organlab.pipeline.write_outputs`, makes the marching-cubes surface and
runs the requested steps; the CLI only calls it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import numpy as np

from .. import validate
from ..bandfield import BandField
from ..errors import OrganlabError
from ..grid import VoxelGrid
from ..session import Session, write_json
from ._aaa import measure_aaa
from ._io import write_obj, write_ply, write_stl, write_vtk
from ._mesh import mesh_from_volume
from ._picture import aaa_picture
from ._repair import finish_surface
from ._tetra import TETRA_FORMATS, tetrahedralize, write_tetra


def is_aaa_session(session: Session) -> bool:
    """True when a session says its specimen is an abdominal aortic aneurysm.

    ``session.json``'s ``reference.specimen`` (or ``specimen``) is ``"aaa"``,
    or, for a synthetic session, its ``truth.json`` names the ``aaa`` phantom.
    """
    raw = getattr(session, "raw", {}) or {}
    for where in (session.reference, raw):
        if str(where.get("specimen", "")).lower() == "aaa":
            return True
    truth = (raw.get("synthetic") or {}).get("truth")
    if truth:
        p = Path(session.root) / truth
        try:
            return json.loads(p.read_text()).get("specimen") == "aaa"
        except (OSError, ValueError):
            return False
    return False


def load_voxels(result_dir: str | Path) -> tuple[np.ndarray, VoxelGrid]:
    """The surface volume and grid of a result folder's ``voxels.npz``.

    Reads the field as stored now (the band: ``field_block``,
    ``field_states``, ``field_values``, see
    :meth:`organlab.carving.BandField.from_arrays`) and as earlier versions
    stored it (a dense ``field``).

    Parameters
    ----------
    result_dir : str or Path
        Output folder of ``organlab reconstruct``.

    Returns
    -------
    volume : (nx, ny, nz) float32
        The sub-voxel field when saved (and no colouring carved the
        occupancy), else the occupancy as 0/1; level 0.5 is the surface.
    grid : VoxelGrid

    Raises
    ------
    OrganlabError
        One line naming the file: missing, unreadable, or an array missing
        or not fitting the others.
    """
    path = Path(result_dir) / "voxels.npz"
    if not path.is_file():
        raise OrganlabError(f"{path}: not found; run 'organlab reconstruct SESSION --out {result_dir}' first")
    fix = "rewrite it with 'organlab reconstruct'"
    # the validated reader: a damaged zip, a pickle or a bad array header is one line naming the file
    z = validate.read_npz(path, fix=fix)
    try:
        occ = z["occupancy"]
        origin = validate.array(z["origin_mm"], (3,), "origin_mm", where=str(path))
        vs = validate.number(z["voxel_size_mm"][()] if z["voxel_size_mm"].shape == () else None,
                              "voxel_size_mm", where=str(path), lo=0, lo_open=True)
    except KeyError as e:
        raise OrganlabError(f"{path}: missing array {e}; {fix}") from None
    if occ.ndim != 3 or occ.dtype.kind not in "bui" or 0 in occ.shape:
        raise OrganlabError(f"{path}: occupancy: {occ.dtype} {occ.shape}, expected (nx, ny, nz) booleans; {fix}")
    if not occ.any():
        raise OrganlabError(f"{path}: occupancy: the model is empty (no voxel kept), there is no surface to "
                            "make; check the reconstruction's warnings and reconstruct again")
    grid = VoxelGrid(origin, vs, occ.shape)
    if "colors" in z:  # colouring carved voxels the field knows nothing of
        vol = occ
    elif "field_states" in z:
        vol = BandField.from_arrays(z, grid, prefix="field_", source=path).dense()
    elif "field" in z:  # written by organlab before the band storage
        vol = z["field"]
        if vol.shape != occ.shape or vol.dtype.kind != "f":
            raise OrganlabError(f"{path}: field: shape {vol.shape}, expected the occupancy's {occ.shape} "
                                f"in floats (got {vol.dtype}); {fix}")
    else:
        vol = occ
    vol = np.asarray(vol, dtype=np.float32)
    if not np.all(np.isfinite(vol)):
        raise OrganlabError(f"{path}: the field holds non-finite numbers; {fix}")
    return vol, grid


def mesh_result(result_dir: str | Path, *, repair: bool = True, smooth: bool = True, remesh: Literal["auto"] | float | None = "auto",
                tetra: bool = False, measure: bool = False, picture: bool = False,
                volume: tuple[np.ndarray, VoxelGrid] | None = None) -> tuple[dict, dict[str, Path]]:
    """Finish the surface of a reconstruction folder and write it (``DIR/surface/``).

    Parameters
    ----------
    result_dir : str or Path
        Output folder of ``organlab reconstruct`` (holds ``voxels.npz``).
    repair, smooth : bool
    remesh : 'auto', float (mm) or None
    tetra : bool
        Also write a tetrahedral mesh as ``tetra.vtu``, ``.msh``, ``.inp``, ``.xdmf``.
    measure : bool
        AAA measurements to ``aaa.json`` (and ``aaa_measures.png`` with ``picture``).
    picture : bool
    volume : ((nx, ny, nz) float32, VoxelGrid), optional
        The volume to mesh (level 0.5) and its grid, as read by the caller
        (``organlab mesh``: :meth:`organlab.engine.Reconstruction.surface_volume`);
        default :func:`load_voxels` of ``result_dir``.

    Returns
    -------
    report : dict
    paths : dict of str -> Path
    """
    vol, grid = load_voxels(result_dir) if volume is None else volume
    if not np.any(vol >= 0.5):
        raise OrganlabError(f"{Path(result_dir) / 'voxels.npz'}: the model is empty (no voxel kept), there is no "
                            "surface to make; check the reconstruction's warnings and reconstruct again")
    out = Path(result_dir) / "surface"
    out.mkdir(parents=True, exist_ok=True)
    raw = mesh_from_volume(vol, grid, level=0.5)
    fin = finish_surface(raw, voxel_size=grid.voxel_size, repair=repair, smooth=smooth, remesh=remesh)
    mesh, report = fin.mesh, fin.to_dict()
    paths = {}
    for name, writer in (("ply", write_ply), ("stl", write_stl), ("obj", write_obj), ("vtu", write_vtk)):
        paths[name] = out / f"mesh.{name}"
        writer(paths[name], mesh)
    if tetra:
        tm, report["tetra"] = tetrahedralize(mesh)
        for ext in TETRA_FORMATS:
            paths[f"tetra_{ext}"] = write_tetra(out / f"tetra.{ext}", tm)
    if measure:
        m = measure_aaa(vol, grid)
        report["aaa"] = m.summary()
        paths["aaa"] = out / "aaa.json"
        write_json(paths["aaa"], {**m.summary(), "centreline_mm": m.centreline.tolist(),
                                  "feret_mm": m.feret_mm.tolist(), "equivalent_mm": m.equivalent_mm.tolist()})
        if picture:
            paths["aaa_picture"] = aaa_picture(mesh, m, out / "aaa_measures.png")
    paths["report"] = out / "surface_report.json"
    write_json(paths["report"], report)
    return report, paths
