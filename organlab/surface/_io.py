"""Mesh files: PLY (with colours), STL, OBJ, VTK legacy and VTU (world frame, mm)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import OrganlabError
from ._mesh import Mesh


def write_ply(path: str | Path, mesh: Mesh) -> None:
    """Write a binary little-endian PLY (vertex colours when the mesh has them).

    Parameters
    ----------
    path : str or Path
    mesh : Mesh
    """
    v = np.asarray(mesh.vertices, dtype="<f4")
    f = np.asarray(mesh.faces)
    colors = mesh.vertex_colors
    header = ["ply", "format binary_little_endian 1.0", "comment organlab mesh, world frame, mm", f"element vertex {len(v)}"]
    header += ["property float x", "property float y", "property float z"]
    vdtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
        vdtype += [("r", "u1"), ("g", "u1"), ("b", "u1")]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    vert = np.empty(len(v), dtype=vdtype)
    vert["x"], vert["y"], vert["z"] = v[:, 0], v[:, 1], v[:, 2]
    if colors is not None:
        c = np.asarray(colors, dtype=np.uint8)
        vert["r"], vert["g"], vert["b"] = c[:, 0], c[:, 1], c[:, 2]
    face = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"] = 3
    face["i"] = f
    with open(Path(path), "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vert.tobytes())
        fh.write(face.tobytes())


def write_stl(path: str | Path, mesh: Mesh) -> None:
    """Write a binary STL (world frame, mm).

    Parameters
    ----------
    path : str or Path
    mesh : Mesh
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces)
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)
    rec = np.zeros(len(f), dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    rec["n"] = n
    rec["v"] = tri
    with open(Path(path), "wb") as fh:
        head = b"organlab mesh, world frame, mm"
        fh.write(head.ljust(80, b" "))
        fh.write(np.uint32(len(f)).tobytes())
        fh.write(rec.tobytes())


def read_ply(path: str | Path) -> Mesh:
    """Read a PLY written by :func:`write_ply` (binary little-endian, triangles).

    Returns
    -------
    Mesh
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise OrganlabError(f"{path}: cannot read ({e.strerror or e}); rewrite it with organlab") from None
    try:
        end = data.index(b"end_header\n") + len(b"end_header\n")
        header = data[:end].decode("ascii").splitlines()
        if not header or header[0] != "ply" or "format binary_little_endian 1.0" not in header:
            raise ValueError("not a binary little-endian PLY")
        nv = nf = 0
        has_color = False
        for line in header:
            parts = line.split()
            if parts[:2] == ["element", "vertex"]:
                nv = int(parts[2])
            elif parts[:2] == ["element", "face"]:
                nf = int(parts[2])
            elif parts[:2] == ["property", "uchar"] and parts[2:3] == ["red"]:
                has_color = True
        if nv < 0 or nf < 0:
            raise ValueError("negative element count")
        vdtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")] + ([("r", "u1"), ("g", "u1"), ("b", "u1")] if has_color else [])
        vert = np.frombuffer(data, dtype=vdtype, count=nv, offset=end)
        off = end + vert.nbytes
        face = np.frombuffer(data, dtype=[("n", "u1"), ("i", "<i4", (3,))], count=nf, offset=off)
    except (ValueError, IndexError, UnicodeDecodeError) as e:  # not a PLY as organlab writes it, or cut short
        raise OrganlabError(f"{path}: not a mesh organlab can read ({e}); rewrite it with organlab") from None
    v = np.stack([vert["x"], vert["y"], vert["z"]], axis=1).astype(np.float64)
    f = face["i"].astype(np.int64)
    if not np.all(np.isfinite(v)) or np.any(face["n"] != 3) or (f.size and (f.min() < 0 or f.max() >= nv)):
        raise OrganlabError(f"{path}: damaged mesh (non-finite vertices, or faces that are not triangles of its "
                            "vertices); rewrite it with organlab")
    c = np.stack([vert["r"], vert["g"], vert["b"]], axis=1) if has_color else None
    return Mesh(v, f, c)


def write_obj(path: str | Path, mesh: Mesh) -> None:
    """Write a Wavefront OBJ (text; world frame, mm; vertex colours as ``v x y z r g b`` in 0-1).

    Parameters
    ----------
    path : str or Path
    mesh : Mesh
    """
    v = np.asarray(mesh.vertices, dtype=np.float64)
    cols = [v]
    fmt = "v %.6f %.6f %.6f"
    if mesh.vertex_colors is not None:
        cols.append(np.asarray(mesh.vertex_colors, dtype=np.float64) / 255.0)
        fmt += " %.4f %.4f %.4f"
    with open(Path(path), "w", encoding="ascii") as fh:
        fh.write("# organlab mesh, world frame, mm\n")
        np.savetxt(fh, np.hstack(cols), fmt=fmt)
        np.savetxt(fh, np.asarray(mesh.faces) + 1, fmt="f %d %d %d")


def read_obj(path: str | Path) -> Mesh:
    """Read the vertices and triangles of an OBJ written by :func:`write_obj`.

    Returns
    -------
    Mesh
    """
    verts, faces = [], []
    for line in Path(path).read_text(encoding="ascii").splitlines():
        parts = line.split()
        if parts[:1] == ["v"]:
            verts.append([float(x) for x in parts[1:4]])
        elif parts[:1] == ["f"]:
            faces.append([int(x.split("/")[0]) - 1 for x in parts[1:4]])
    return Mesh(np.array(verts, dtype=np.float64).reshape(-1, 3), np.array(faces, dtype=np.int64).reshape(-1, 3))


def write_vtk(path: str | Path, mesh: Mesh) -> Path:
    """Write a triangle mesh as VTK: legacy ``.vtk`` or XML ``.vtu`` after the suffix (meshio).

    Parameters
    ----------
    path : str or Path
        Ends in ``.vtk`` or ``.vtu``.
    mesh : Mesh
    """
    import meshio

    path = Path(path)
    fmt = {".vtk": "vtk", ".vtu": "vtu"}.get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"{path}: write_vtk writes .vtk or .vtu files")
    point_data = {}
    if mesh.vertex_colors is not None:
        point_data["rgb"] = np.asarray(mesh.vertex_colors, dtype=np.uint8)
    m = meshio.Mesh(np.asarray(mesh.vertices, np.float64), [("triangle", np.asarray(mesh.faces))], point_data=point_data)
    meshio.write(path, m, file_format=fmt)
    return path
