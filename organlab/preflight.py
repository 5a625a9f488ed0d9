"""Checks before the long work, and outputs written atomically.

A run must not die after minutes on something it could have seen at the
start (an output path that is a file, a grid that cannot fit in memory, an
infinite voxel size), and must never leave a half-written output folder next
to the previous result.

- :func:`check_voxel_size`, :func:`check_grid_memory`: numbers finite and the
  voxel grid's memory within a limit (default: the memory available now),
  refused with the largest voxel size that fits.
- :func:`check_output_dir`: ``--out`` is not a file, is (or can be) a folder
  organlab may replace, and its parent is writable.
- :func:`atomic_output_dir`: a temporary folder beside ``--out``, moved into
  place only when everything was written; on any exception (Ctrl-C included)
  the previous result stays as it was and the temporary folder is removed.
- :func:`lock_output_dir`: one run at a time into an ``--out`` (a lock file
  beside it, released by the kernel even after kill -9); a second run refuses.
- :func:`recover_output_dir`: what a killed run left beside ``--out`` (the
  previous result moved aside, a half-written temporary folder) is restored or
  removed on the next run, which says so.
"""

from __future__ import annotations

import errno
import fnmatch
import math
import os
import re
import shutil
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .errors import OrganlabError, SessionError

__all__ = [
    "OUTPUT_NAMES",
    "SURFACE_PATTERNS",
    "atomic_output_dir",
    "lock_output_dir",
    "recover_output_dir",
    "IMAGE_BYTES_PER_PIXEL",
    "REMESH_BYTES_PER_FACE",
    "check_remesh_memory",
    "bytes_per_voxel",
    "check_image_memory",
    "image_header_size",
    "check_grid_memory",
    "check_output_dir",
    "check_voxel_size",
    "available_memory",
    "parse_memory",
]

#: Files organlab writes into an output folder; a folder holding only these
#: (or empty) may be replaced by a new run.
OUTPUT_NAMES = frozenset(
    {"report.json", "voxels.npz", "mesh.ply", "mesh.stl", "calibration.json", "mesh.png", "agreement.png", "surface",
     "worst_view.png"}
)
#: Files ``organlab mesh`` writes into ``--out/surface/``: a file there matching none of these is
#: the user's, and a run refuses to replace the folder rather than delete it.
SURFACE_PATTERNS = ("mesh.*", "tetra.*", "aaa.json", "aaa_measures.png", "surface_report.json")


def check_voxel_size(voxel_size, *, name="--voxel-size"):
    """A finite, positive voxel size in mm, as float; SessionError otherwise."""
    if isinstance(voxel_size, bool) or not isinstance(voxel_size, (int, float, np.integer, np.floating)):
        raise SessionError(f"{name} must be a positive number of mm, got {voxel_size!r}")
    if not (math.isfinite(voxel_size) and voxel_size > 0):
        raise SessionError(f"{name} must be a finite number of mm > 0, got {voxel_size!r}")
    return float(voxel_size)


def bytes_per_voxel(*, method="hull", tolerance=0):
    """Peak memory of the pipeline per voxel, bytes (an upper estimate).

    The sub-voxel hull field holds ``(tolerance + 1) * 4 + 2`` bytes per voxel
    while it accumulates, then float64 intermediates (8 + 8), the float32
    field and the bool occupancy; colouring adds colours, flags and depth
    buffers of about as much again.  Measured on the sample session (peak
    resident memory less the 0.34 GB of a run at 4 mm): 28 bytes per voxel
    at 1 mm (3.9 M voxels), 29 at 0.5 mm (31 M voxels); 40 leaves a margin.
    """
    base = 40 + 4 * int(tolerance)
    return base * 2 if method != "hull" else base


def available_memory():
    """Memory available to this process now, bytes (the kernel's MemAvailable; psutil elsewhere; 4 GiB if unknown).

    /proc/meminfo first: on Linux psutil reads the same line, and importing it cost 19 ms of the command's
    start-up (issue 24).
    """
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:  # not Linux (or a kernel before 3.14): psutil's estimate
        import psutil

        return int(psutil.virtual_memory().available)
    except Exception:  # noqa: BLE001 (psutil missing or unusable)
        return 4 << 30


_UNITS = {"": 1, "b": 1, "k": 1 << 10, "kb": 1 << 10, "kib": 1 << 10, "m": 1 << 20, "mb": 1 << 20, "mib": 1 << 20,
          "g": 1 << 30, "gb": 1 << 30, "gib": 1 << 30, "t": 1 << 40, "tb": 1 << 40, "tib": 1 << 40}


def parse_memory(text):
    """``'8G'``, ``'512M'``, ``'2.5GiB'``, ``'1000000'`` (bytes) -> bytes (int); SessionError otherwise."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:e[+-]?[0-9]+)?)\s*([a-zA-Z]*)\s*", str(text))
    unit = m.group(2).lower() if m else None
    if not m or unit not in _UNITS:
        raise SessionError(f"--max-memory: not a memory size: {text!r} (e.g. 8G, 512M)")
    value = float(m.group(1)) * _UNITS[unit]
    if not (math.isfinite(value) and value > 0):
        raise SessionError(f"--max-memory must be > 0, got {text!r}")
    return int(value)


def _n_voxels(extent, voxel_size):
    return float(np.prod(np.maximum(1, np.ceil(extent / voxel_size - 1e-9))))


def _fmt_bytes(n):
    for unit, f in (("TiB", 1 << 40), ("GiB", 1 << 30), ("MiB", 1 << 20)):
        if n >= f:
            return f"{n / f:.1f} {unit}"
    return f"{n / 1024:.0f} KiB"


def check_grid_memory(roi_min, roi_max, voxel_size, *, max_memory=None, method="hull", tolerance=0, where="session"):
    """Refuse a voxel grid whose estimated memory exceeds a limit.

    Parameters
    ----------
    roi_min, roi_max : (3,) float, mm, world frame
    voxel_size : float, mm
    max_memory : int, optional
        Bytes; default :func:`available_memory`.
    method : str
        ``'hull'``, ``'coloring'`` or ``'space_carving'`` (see :func:`bytes_per_voxel`).
    tolerance : int
    where : str
        Named in the message (the session's ``session.json``).

    Returns
    -------
    int
        Estimated bytes.

    Raises
    ------
    SessionError
        One line with the estimate, the limit and the largest voxel size that fits.
    """
    voxel_size = check_voxel_size(voxel_size)
    extent = np.asarray(roi_max, dtype=np.float64) - np.asarray(roi_min, dtype=np.float64)
    limit = available_memory() if max_memory is None else int(max_memory)
    per = bytes_per_voxel(method=method, tolerance=tolerance)
    need = _n_voxels(extent, voxel_size) * per
    if need <= limit:
        return int(need)
    # smallest voxel size (2 significant digits, rounded up) whose grid fits
    vs = (float(np.prod(extent)) * per / limit) ** (1 / 3)
    for _ in range(200):
        step = 10 ** (math.floor(math.log10(vs)) - 1)
        vs = math.ceil(vs / step - 1e-9) * step
        if _n_voxels(extent, vs) * per <= limit:
            break
        vs += step
    shape = "x".join(str(int(v)) for v in np.maximum(1, np.ceil(extent / voxel_size - 1e-9)))
    src = "--max-memory" if max_memory is not None else "the memory available now"
    raise SessionError(
        f"{where}: roi: a {shape} grid at {voxel_size:g} mm needs about {_fmt_bytes(need)}, more than "
        f"{_fmt_bytes(limit)} ({src}); use --voxel-size {vs:.3g} or more, a smaller roi, or raise --max-memory"
    )


#: Peak memory of the pipeline per pixel of every view, bytes, before the voxel grid: the RGB
#: image (3), the silhouette model's coverage, distance and mask arrays.  Measured with
#: tracemalloc on a 320x240 synthetic session (12 views, 5 background frames): 3.0 B/px after
#: reading the views, 61 held and 67 at the peak after the silhouettes; 70 leaves a margin.
IMAGE_BYTES_PER_PIXEL = 70


def image_header_size(path):
    """``(width, height)`` of a PNG or JPEG from its header, without decoding it (None if unknown).

    Examples
    --------
    >>> import tempfile, pathlib, cv2, numpy as np
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "a.png"
    >>> _ = cv2.imwrite(str(p), np.zeros((3, 5), np.uint8))
    >>> image_header_size(p)
    (5, 3)
    """
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 20)  # headers: PNG 24 bytes; a JPEG's SOF follows its EXIF/ICC segments (< 1 MB)
    except OSError:
        return None
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if head[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 < len(head):
        if head[i] != 0xFF:
            return None
        marker = head[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        length = int.from_bytes(head[i + 2:i + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # start of frame
            return int.from_bytes(head[i + 7:i + 9], "big"), int.from_bytes(head[i + 5:i + 7], "big")
        i += 2 + length
    return None


def check_image_memory(image_size, n_images, *, max_memory=None, where="session"):
    """Refuse views whose decoding and silhouettes would not fit in memory, before any is decoded.

    Parameters
    ----------
    image_size : (2,) int
        ``(width, height)`` px of every view (checked against each file's header when
        the session is loaded).
    n_images : int
        Views read at once.
    max_memory : int, optional
        Bytes; default :func:`available_memory`.
    where : str

    Returns
    -------
    int
        Estimated bytes (:data:`IMAGE_BYTES_PER_PIXEL` per pixel of every view).

    Raises
    ------
    SessionError
    """
    w, h = (int(v) for v in image_size)
    need = float(w) * h * int(n_images) * IMAGE_BYTES_PER_PIXEL
    limit = available_memory() if max_memory is None else int(max_memory)
    if need > limit:
        src = "--max-memory" if max_memory is not None else "the memory available now"
        raise SessionError(
            f"{where}: image_size: {n_images} views of {w}x{h} px need about {_fmt_bytes(need)} to read and "
            f"segment, more than {_fmt_bytes(limit)} ({src}); downscale the images, use fewer views, or raise "
            "--max-memory")
    return int(need)


#: Peak memory of repairing and remeshing, bytes per face of the remeshed surface: measured with
#: ``ru_maxrss`` on a 40 mm ball (2 mm voxels) remeshed to 0.25 mm edges: 172 722 faces, +206 MB
#: (1 249 B/face); rounded up.
REMESH_BYTES_PER_FACE = 1300


def check_remesh_memory(area_mm2, edge_mm, *, max_memory=None, where="--remesh"):
    """Refuse a remeshing whose surface would not fit in memory, before it starts.

    An isotropic mesh of edges ``e`` has about ``area / (0.433 e^2)`` faces (equilateral
    triangles; 180 702 predicted for the 172 722 measured above).

    Parameters
    ----------
    area_mm2 : float
        Surface area, mm^2 (an upper bound: the voxels' staircase area is 1.2-1.5x the smooth one).
    edge_mm : float
        Target edge length, mm.
    max_memory : int, optional
        Bytes; default :func:`available_memory`.

    Returns
    -------
    int
        Estimated bytes.

    Raises
    ------
    SessionError
        One line with the smallest edge that fits.
    """
    faces = float(area_mm2) / (0.433 * float(edge_mm) ** 2)
    need = faces * REMESH_BYTES_PER_FACE
    limit = available_memory() if max_memory is None else int(max_memory)
    if need > limit:
        smallest = math.sqrt(float(area_mm2) * REMESH_BYTES_PER_FACE / (0.433 * limit))
        raise SessionError(f"{where} {edge_mm:g}: about {faces / 1e6:.3g} million faces, about {_fmt_bytes(need)} "
                           f"to remesh, more than {_fmt_bytes(limit)} available; give --remesh {smallest:.2g} or more")
    return int(need)


def _foreign_files(path):
    """Entries of an output folder organlab did not write (relative names, sorted)."""
    others = sorted(p.name for p in path.iterdir() if p.name not in OUTPUT_NAMES)
    surface = path / "surface"
    if surface.is_symlink() or (surface.exists() and not surface.is_dir()):
        others.append("surface")
    elif surface.is_dir():
        others += sorted(f"surface/{p.name}" for p in surface.iterdir()
                         if p.is_symlink() or not p.is_file() or not any(fnmatch.fnmatchcase(p.name, pat) for pat in SURFACE_PATTERNS))
    for name in OUTPUT_NAMES - {"surface"}:  # organlab writes files there, never folders or links
        p = path / name
        if p.is_symlink() or p.is_dir():
            others.append(name)
    return others


def check_output_dir(out):
    """Check that ``out`` can receive a run's outputs, before the long work.

    ``out`` must not be a file; an existing folder must be empty or hold
    only organlab outputs (:data:`OUTPUT_NAMES`), which a run replaces as a
    whole; its parent folder must be writable (tried by creating and
    removing a temporary folder there).

    Returns
    -------
    Path
        ``out``, absolute.

    Raises
    ------
    OrganlabError
    """
    out = Path(out).absolute()
    if out.exists() and not out.is_dir():
        raise OrganlabError(f"{out}: --out exists and is not a folder; give a folder path")
    others = _foreign_files(out) if out.is_dir() else []
    if others:
        raise OrganlabError(
            f"{out}: --out holds files organlab did not write ({', '.join(others[:3])}"
            f"{', ...' if len(others) > 3 else ''}); give an empty or new folder"
        )
    parent = out.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryDirectory(dir=parent, prefix=f".{out.name}.check-").cleanup()
    except OSError as e:
        raise OrganlabError(f"{parent}: cannot write the output folder here ({e.strerror or e}); choose another --out") from None
    return out


_held = {}  # out path -> depth of lock_output_dir in this process
_held_lock = threading.Lock()


def _lock_path(out):
    return out.parent / f".{out.name}.lock"


@contextmanager
def lock_output_dir(out, *, required=True):
    """Hold the lock of an output folder while a run writes it; recover what a killed run left.

    The lock is an exclusive ``flock`` on ``.NAME.lock`` beside ``out``: the kernel
    releases it when the process ends, kill -9 included, so a stale lock file never
    blocks a later run (which removes it when done).  Re-entrant within a process.

    Parameters
    ----------
    out : str or Path
    required : bool
        False: when the lock file cannot be created (a read-only parent folder), go on
        without it (for commands that write only inside ``out``).

    Yields
    ------
    list of str
        What :func:`recover_output_dir` restored or removed (empty when nothing).

    Raises
    ------
    OrganlabError
        Another run holds the lock (its process id named).
    """
    import fcntl

    out = Path(out).absolute()
    with _held_lock:
        if _held.get(out):
            _held[out] += 1
            nested = True
        else:
            nested = False
    if nested:
        try:
            yield []
        finally:
            with _held_lock:
                _held[out] -= 1
        return
    path = _lock_path(out)
    for _ in range(10):  # the file may be removed by the run that held it between open and lock
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            if not required:
                yield []
                return
            raise OrganlabError(f"{path}: cannot create the lock of --out ({e.strerror}); choose a writable --out") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            os.close(fd)
            if e.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise
            try:
                pid = path.read_text().strip() or "?"
            except OSError:
                pid = "?"
            raise OrganlabError(f"{out}: another organlab run (process {pid}) is writing this --out; wait for it "
                                "to finish or give another --out") from None
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    else:
        raise OrganlabError(f"{path}: the lock of --out keeps changing; is another run starting? try again")
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        with _held_lock:
            _held[out] = 1
        try:
            yield recover_output_dir(out)
        finally:
            with _held_lock:
                _held.pop(out, None)
            try:
                os.unlink(path)  # before the unlock: a waiting run then finds the file gone and retries
            except OSError:
                pass
    finally:
        os.close(fd)


def recover_output_dir(out):
    """Restore or remove what an interrupted run left beside ``out``.

    A run killed between moving the previous result aside (``.NAME.old-*``) and moving
    the new one in leaves no ``out``: the previous result is moved back.  A previous
    result left aside when ``out`` exists, and half-written temporary folders
    (``.NAME.tmp-*``, ``.NAME.check-*``), are removed.  Call it holding
    :func:`lock_output_dir` (it does).

    Returns
    -------
    list of str
        One line per thing restored or removed.
    """
    out = Path(out).absolute()
    parent = out.parent
    if not parent.is_dir():
        return []
    notes = []
    olds = sorted(parent.glob(f".{_glob_escape(out.name)}.old-*"), key=lambda p: p.stat().st_mtime, reverse=True)
    olds = [p for p in olds if p.is_dir() and not p.is_symlink()]
    if olds and not out.exists():
        os.rename(olds[0], out)
        notes.append(f"restored the previous result {out} from {olds[0].name} (a run was interrupted while "
                     "replacing it)")
        olds = olds[1:]
    for p in olds:
        shutil.rmtree(p, ignore_errors=True)
        notes.append(f"removed {p.name}, a previous result an interrupted run had moved aside")
    for pattern in (".{}.tmp-*", ".{}.check-*"):
        for p in sorted(parent.glob(pattern.format(_glob_escape(out.name)))):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
                notes.append(f"removed {p.name}, the unfinished output of an interrupted run")
    return notes


def _glob_escape(name):
    """``name`` with glob's special characters escaped (``[``, ``*``, ``?``)."""
    return re.sub(r"([\[\]*?])", r"[\1]", name)


@contextmanager
def atomic_output_dir(out):
    """A temporary folder beside ``out`` that replaces ``out`` when the block completes.

    Write every output into the yielded folder.  When the ``with`` block ends
    normally, a previous ``out`` is moved aside, the new folder renamed to
    ``out`` and the old one removed: no file of an earlier run is left mixed
    with the new ones.  When the block raises (Ctrl-C included), the
    temporary folder is removed and ``out`` is untouched.  The whole block holds
    :func:`lock_output_dir` (a concurrent run refuses), and a killed earlier run's
    leftovers are recovered first (:func:`recover_output_dir`).

    Parameters
    ----------
    out : str or Path
        Checked with :func:`check_output_dir`.

    Yields
    ------
    Path
    """
    with lock_output_dir(out):
        out = check_output_dir(out)
        tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp-"))
        try:
            yield tmp
            os.chmod(tmp, 0o777 & ~_umask())
            old = None
            if out.exists():
                old = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.old-"))
                os.rmdir(old)
                os.rename(out, old)
            try:
                os.rename(tmp, out)
            except OSError:
                if old is not None:
                    os.rename(old, out)  # put the previous result back
                raise
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        except OSError as e:  # a full disk, a folder made read-only meanwhile: one line, the previous result intact
            shutil.rmtree(tmp, ignore_errors=True)
            what = f" ({e.filename})" if e.filename else ""
            raise OrganlabError(f"{out}: cannot write the outputs: {e.strerror or e}{what}; free some space or choose "
                                "another --out (a previous result there is left as it was)") from None
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise


def _umask():
    m = os.umask(0)
    os.umask(m)
    return m
