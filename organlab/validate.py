"""One validation layer for the files organlab reads (ground floor: numpy and organlab.errors only).

Every reader of a user's file (``session.json``, ``calibration.json``, ``voxels.npz``, meshes,
camera files) goes through these helpers, so that a malformed file of any kind ends in one
line naming the file, the key and the fix (:class:`~organlab.errors.OrganlabError` or a
subclass), never in a traceback, a hang or a silently wrong number:

- :func:`read_json`: bounded size and nesting depth (checked before parsing: Python's parser
  recurses), strict JSON (``NaN``/``Infinity`` refused), UTF-8.
- :func:`read_npz`: an ``.npz`` of plain arrays (never pickles), its decompressed size bounded
  from the zip's directory before anything is decompressed.
- :func:`number`, :func:`integer`, :func:`array`, :func:`string`: types, finiteness, ranges.
- :func:`inside`: a path a file names, resolved inside its folder (symlinks followed) or refused.
- :func:`printable`: text from a file, control characters escaped, before it reaches a terminal.
"""

from __future__ import annotations

import json
import math
import re
import zipfile
import zlib
from pathlib import Path

import numpy as np

from .errors import OrganlabError

__all__ = ["MAX_DEPTH", "MAX_JSON_BYTES", "read_json", "read_npz", "json_depth", "number", "integer", "array",
           "string", "inside", "printable"]

#: Deepest nesting accepted in a JSON file organlab reads.  Its own files nest at most 5 deep
#: (calibration.json: turntable.images.NAME.corners_px[i][j]); Python's parser fails with a
#: RecursionError near 1000.
MAX_DEPTH = 64
#: Largest JSON file read, bytes.  A calibration.json of 60 board images with their corners
#: is about 0.6 MB; a session.json of 3600 views about 0.5 MB.
MAX_JSON_BYTES = 64 << 20

_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.S)


def json_depth(data):
    """Deepest ``[``/``{`` nesting of JSON text (bytes or str), strings ignored; without parsing."""
    if isinstance(data, str):
        data = data.encode("utf-8", "surrogatepass")
    b = np.frombuffer(_STRING.sub(b'""', data), dtype=np.uint8)
    step = (b == ord("[")).astype(np.int32) + (b == ord("{")) - (b == ord("]")) - (b == ord("}"))
    return int(np.cumsum(step).max()) if step.size else 0


def _no_constant(name):
    raise ValueError(f"{name} is not JSON (write a number or null)")


def read_json(path, *, error=OrganlabError, fix="fix or regenerate it", max_depth=MAX_DEPTH, max_bytes=MAX_JSON_BYTES):
    """Read a JSON file strictly, with one-line errors.

    Parameters
    ----------
    path : str or Path
    error : type
        The exception raised (an :class:`OrganlabError` subclass).
    fix : str
        What the user should do, ending the message.
    max_depth, max_bytes : int
        Limits on nesting and size.

    Returns
    -------
    object
        The parsed document (dict, list, str, int, float, bool or None).

    Raises
    ------
    error
        Missing, unreadable, too big, too deep, not UTF-8, not strict JSON.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "a.json"
    >>> _ = p.write_text('{"a": [1, 2]}')
    >>> read_json(p)
    {'a': [1, 2]}
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise error(f"{path}: {size} bytes, more than the {max_bytes} a JSON file organlab reads may have; {fix}")
        data = path.read_bytes()
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except IsADirectoryError:
        raise error(f"{path}: is a folder, not a JSON file") from None
    except OSError as e:
        raise error(f"{path}: cannot read ({e.strerror or e}); {fix}") from None
    depth = json_depth(data)
    if depth > max_depth:
        raise error(f"{path}: nested {depth} deep, more than the {max_depth} organlab reads; {fix}")
    try:
        return json.loads(data.decode("utf-8"), parse_constant=_no_constant)
    except UnicodeDecodeError:
        raise error(f"{path}: not a UTF-8 text file; {fix}") from None
    except json.JSONDecodeError as e:
        raise error(f"{path}: invalid JSON at line {e.lineno} column {e.colno}: {e.msg}; {fix}") from None
    except (ValueError, RecursionError) as e:
        raise error(f"{path}: invalid JSON: {e}; {fix}") from None


def read_npz(path, *, error=OrganlabError, fix="fix or regenerate it", max_bytes=None, kinds="biuf"):
    """The arrays of an ``.npz`` file, read without pickles and with its memory bounded first.

    Parameters
    ----------
    path : str or Path
    error : type
        The exception raised (an :class:`OrganlabError` subclass).
    fix : str
        What the user should do, ending the message.
    max_bytes : int, optional
        Largest total decompressed size, bytes, checked from the zip's directory before any
        array is decompressed (a small file may hold a huge array); default no bound.
    kinds : str
        The numpy dtype kinds accepted (``'b'`` bool, ``'i'``/``'u'`` integers, ``'f'`` floats).

    Returns
    -------
    dict of str -> ndarray

    Raises
    ------
    error
        Missing, unreadable, not a zip of ``.npy`` arrays, an array's header or data damaged,
        an object or other dtype, more than ``max_bytes``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "a.npz"
    >>> np.savez(p, a=np.arange(3))
    >>> read_npz(p)["a"]
    array([0, 1, 2])
    """
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: {'is a folder, not a file' if path.is_dir() else 'no such file'}; {fix}")
    try:
        with open(path, "rb") as f, zipfile.ZipFile(f) as zf:
            infos = zf.infolist()
            total = sum(i.file_size for i in infos)
            if max_bytes is not None and total > max_bytes:
                raise error(f"{path}: its arrays take {_size(total)} decompressed, more than the "
                            f"{_size(max_bytes)} of memory available; {fix} (or free memory)")
            out = {}
            for info in infos:
                name = info.filename
                if not name.endswith(".npy") or name.count("/") or len(name) > 260:
                    raise error(f"{path}: holds {printable(name[:60])!r}, not an array organlab writes; {fix}")
                with zf.open(info) as member:
                    version = np.lib.format.read_magic(member)
                    readers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
                    if version not in readers:
                        raise error(f"{path}: {name[:-4]}: .npy format {version}, not one organlab writes; {fix}")
                    try:  # numpy parses the header with ast and tokenize: any of their errors
                        shape, fortran, dtype = readers[version](member, max_header_size=10000)
                    except Exception as e:  # noqa: BLE001 -- a damaged header is one line naming the array
                        raise error(f"{path}: {name[:-4]}: damaged array header ({type(e).__name__}); {fix}") from None
                    if dtype.hasobject or dtype.kind not in kinds or dtype.fields is not None:
                        raise error(f"{path}: {name[:-4]}: dtype {dtype}, not plain numbers; {fix}")
                    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize if shape else dtype.itemsize
                    if nbytes != info.file_size - member.tell():
                        raise error(f"{path}: {name[:-4]}: its header says {shape} {dtype}, the data does not fit; {fix}")
                    data = member.read(nbytes)
                if len(data) != nbytes:
                    raise error(f"{path}: {name[:-4]}: cut short; {fix}")
                a = np.frombuffer(data, dtype=dtype)
                out[name[:-4]] = (a.reshape(shape[::-1]).T if fortran else a.reshape(shape)).copy()
            return out
    except OrganlabError:
        raise
    except (OSError, ValueError, TypeError, IndexError, EOFError, OverflowError, MemoryError, SyntaxError,
            zipfile.BadZipFile, zipfile.LargeZipFile, NotImplementedError, zlib.error) as e:
        raise error(f"{path}: unreadable ({type(e).__name__}: {printable(str(e))[:120]}); {fix}") from None


def _size(n):
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"


def _short(v):
    try:
        s = repr(v)
    except Exception:  # a value whose repr fails is shown by its type
        s = f"<{type(v).__name__}>"
    return printable(s if len(s) < 40 else s[:37] + "...")


def number(value, key, *, error=OrganlabError, where="", lo=None, hi=None, lo_open=False, required=True, default=None):
    """A finite real number (not a bool) within ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``), as float.

    ``None`` gives ``default`` unless ``required``.

    Examples
    --------
    >>> number(2, "x", lo=0)
    2.0
    """
    if value is None and not required:
        return default
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    if ok:
        try:
            v = float(value)
        except OverflowError:  # an int beyond float
            ok = False
    if not ok or not math.isfinite(v):
        raise error(f"{where}{': ' if where else ''}{key}: must be a finite number, got {_short(value)}")
    if (lo is not None and (v <= lo if lo_open else v < lo)) or (hi is not None and v > hi):
        rng = f"{'>' if lo_open else '>='} {lo:g}" if hi is None else f"in {'(' if lo_open else '['}{lo:g}, {hi:g}]"
        if lo is None:
            rng = f"<= {hi:g}"
        raise error(f"{where}{': ' if where else ''}{key}: must be {rng}, got {_short(value)}")
    return v


def integer(value, key, *, error=OrganlabError, where="", lo=None, hi=None):
    """An int (not a bool) within ``[lo, hi]``.

    Examples
    --------
    >>> integer(3, "n", lo=1)
    3
    """
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise error(f"{where}{': ' if where else ''}{key}: must be an integer, got {_short(value)}")
    v = int(value)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        rng = f">= {lo}" if hi is None else (f"<= {hi}" if lo is None else f"in [{lo}, {hi}]")
        raise error(f"{where}{': ' if where else ''}{key}: must be {rng}, got {v}")
    return v


def array(value, shape, key, *, error=OrganlabError, where="", lo=None, hi=None):
    """A finite float64 array of ``shape`` (``-1`` in it: any length) from nested lists of numbers.

    Examples
    --------
    >>> array([[1, 2]], (-1, 2), "c").shape
    (1, 2)
    """
    pre = f"{where}{': ' if where else ''}{key}"
    if isinstance(value, (str, bytes, dict, bool)) or value is None:
        raise error(f"{pre}: must be numbers of shape {_shape(shape)}, got {_short(value)}")
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError, RecursionError):
        raise error(f"{pre}: must be numbers of shape {_shape(shape)}, got {_short(value)}") from None
    if a.ndim != len(shape) or any(s != -1 and s != n for s, n in zip(shape, a.shape)):
        raise error(f"{pre}: must have shape {_shape(shape)}, got {tuple(a.shape)}")
    if _has_bool(value):
        raise error(f"{pre}: must be numbers, not true/false")
    if not np.all(np.isfinite(a)):
        raise error(f"{pre}: must hold finite numbers")
    if (lo is not None and np.any(a < lo)) or (hi is not None and np.any(a > hi)):
        raise error(f"{pre}: values must be in [{lo}, {hi}]")
    return a


def _has_bool(v):
    if isinstance(v, bool):
        return True
    if isinstance(v, (list, tuple)):
        return any(_has_bool(x) for x in v[:64])  # a sample: the shape check already bounded the rest's type
    return False


def _shape(shape):
    return "(" + ", ".join("N" if s == -1 else str(s) for s in shape) + ")"


def string(value, key, *, error=OrganlabError, where="", max_len=4096):
    """A str of at most ``max_len`` characters.

    Examples
    --------
    >>> string("a", "name")
    'a'
    """
    if not isinstance(value, str) or len(value) > max_len:
        raise error(f"{where}{': ' if where else ''}{key}: must be text of at most {max_len} characters, got {_short(value)}")
    return value


def inside(root, relative, key, *, error=OrganlabError, where="", allow_outside=False):
    """``root / relative`` resolved (symlinks followed), refused when it leaves ``root``.

    Parameters
    ----------
    root : Path
        The folder the file names paths in (resolved).
    relative : str
        The path as written in the file.
    allow_outside : bool
        Accept a path outside ``root`` (absolute, ``..``, or a symlink out).

    Returns
    -------
    Path, absolute

    Examples
    --------
    >>> inside(Path("/tmp"), "a.png", "image")
    PosixPath('/tmp/a.png')
    """
    root = Path(root).resolve()
    if not isinstance(relative, str) or not relative or "\x00" in relative:
        raise error(f"{where}{': ' if where else ''}{key}: must be a path (text), got {_short(relative)}")
    p = root / relative
    try:
        real = p.resolve()
    except (OSError, RuntimeError) as e:  # a symlink loop
        raise error(f"{where}{': ' if where else ''}{key}: cannot resolve '{printable(relative)}' ({e})") from None
    if not allow_outside and not real.is_relative_to(root):
        raise error(f"{where}{': ' if where else ''}{key}: '{printable(relative)}' is outside the session folder "
                    f"{root}; copy the file into it (or allow outside paths explicitly)")
    return real if allow_outside else p


_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029\u202a-\u202e\u2066-\u2069]")


def printable(text):
    """``text`` with control characters (terminal escapes, newlines, bidi overrides) escaped.

    Examples
    --------
    >>> printable("a\\x1b[2Jb")
    'a\\\\x1b[2Jb'
    """
    return _CONTROL.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), str(text))
