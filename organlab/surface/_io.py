"""Mesh files: PLY (with colours), STL, OBJ, VTK legacy and VTU (world frame, mm)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._mesh import Mesh


def write_ply(path, mesh):
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


def write_stl(path, mesh):
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


def read_ply(path):
    """Read a PLY written by :func:`write_ply` (binary little-endian, triangles).

    Returns
    -------
    Mesh
    """
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    nv = nf = 0
    has_color = False
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            nv = int(parts[2])
        elif parts[:2] == ["element", "face"]:
            nf = int(parts[2])
        elif parts[:2] == ["property", "uchar"] and parts[2] == "red":
            has_color = True
    vdtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")] + ([("r", "u1"), ("g", "u1"), ("b", "u1")] if has_color else [])
    vert = np.frombuffer(data, dtype=vdtype, count=nv, offset=end)
    off = end + vert.nbytes
    face = np.frombuffer(data, dtype=[("n", "u1"), ("i", "<i4", (3,))], count=nf, offset=off)
    v = np.stack([vert["x"], vert["y"], vert["z"]], axis=1).astype(np.float64)
    c = np.stack([vert["r"], vert["g"], vert["b"]], axis=1) if has_color else None
    return Mesh(v, face["i"].astype(np.int64), c)
