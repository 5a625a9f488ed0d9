"""OpenCV's ``FileStorage`` files (YAML 1.0 and XML) read as plain Python, without OpenCV's parser.

``cv2.FileStorage`` aborts the whole process on some damaged files (``Fatal Python error: Aborted`` in
``release()``, seen under the readers' fuzz test), so a damaged calibration file could end a run, a
notebook kernel or a viewer with no message.  The files organlab reads are small maps of numbers,
strings, sequences and ``opencv-matrix`` nodes; this module parses them with PyYAML's safe loader (a
dependency of dask, already pinned) and :mod:`xml.etree.ElementTree` (expat refuses entity expansion
attacks), and every failure is a :class:`~organlab.errors.CalibrationError` naming the file.  Writing
still goes through ``cv2.FileStorage``, whose output both parsers read.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..errors import CalibrationError

#: Larger files are refused before parsing (a calibration file is a few kB; 1 000 views of poses ~ 0.5 MB).
MAX_BYTES = 16 * 2**20
#: Matrix elements refused beyond this (a camera matrix has 9, 1 000 poses 6 000).
MAX_ELEMENTS = 10**6

_DTYPES = {"u": np.uint8, "c": np.int8, "w": np.uint16, "s": np.int16, "i": np.int32, "f": np.float32, "d": np.float64}


def read_storage(path: str | Path) -> dict[str, Any]:
    """The top-level map of an OpenCV YAML or XML file.

    Parameters
    ----------
    path : str or Path
        A file written by ``cv2.FileStorage`` (``%YAML:1.0`` or ``<opencv_storage>``).

    Returns
    -------
    dict
        Keys to values: ``int``, ``float``, ``str``, ``list``, ``dict``, or a float64 ``numpy.ndarray``
        of shape ``(rows, cols)`` for an ``opencv-matrix`` node.

    Raises
    ------
    CalibrationError
        One line naming the file when it is too large, not UTF-8, or not such a file.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "k.yml"
    >>> _ = p.write_text("%YAML:1.0\\n---\\nimage_width: 640\\nK: !!opencv-matrix\\n   rows: 1\\n   cols: 2\\n"
    ...                  "   dt: d\\n   data: [ 1., 2. ]\\n")
    >>> d = read_storage(p)
    >>> d["image_width"], d["K"].tolist()
    (640, [[1.0, 2.0]])
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_BYTES:
            raise CalibrationError(f"{path}: {size} bytes is too large for an OpenCV calibration file "
                                   f"(at most {MAX_BYTES} bytes)")
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise CalibrationError(f"{path}: is not UTF-8 text; give an OpenCV calibration YAML/XML file") from None
    except OSError as e:
        raise CalibrationError(f"{path}: cannot be read ({e.strerror or e})") from None
    try:
        head = text.lstrip("\ufeff \t\r\n")
        doc = _read_xml(head) if head.startswith("<") else _read_yaml(head)
    except CalibrationError as e:
        raise CalibrationError(f"{path}: {e}") from None
    except (yaml.YAMLError, ET.ParseError, RecursionError, ValueError, TypeError, OverflowError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CalibrationError(f"{path}: cannot be parsed as OpenCV YAML/XML ({first})") from None
    if not isinstance(doc, dict):
        raise CalibrationError(f"{path}: cannot be parsed as OpenCV YAML/XML (its top level is not a map)")
    return doc


def _matrix(rows, cols, dt, data):
    try:
        rows, cols = int(rows), int(cols)
    except (TypeError, ValueError):
        raise CalibrationError("an opencv-matrix needs integer rows and cols") from None
    if rows < 0 or cols < 0 or rows * cols > MAX_ELEMENTS:
        raise CalibrationError(f"an opencv-matrix of {rows} x {cols} is out of range")
    if not isinstance(dt, str) or not dt or dt[-1] not in _DTYPES:
        raise CalibrationError(f"an opencv-matrix has an unknown dt {dt!r}")
    channels = int(dt[:-1]) if dt[:-1].isdigit() else 1
    values = np.asarray([_number(v) for v in (data if isinstance(data, list) else [data])], dtype=np.float64)
    if values.size != rows * cols * channels:
        raise CalibrationError(f"an opencv-matrix of {rows} x {cols} has {values.size} values")
    return values.reshape(rows, cols * channels) if channels == 1 else values.reshape(rows, cols, channels)


_SPECIAL = {".nan": np.nan, ".inf": np.inf, "+.inf": np.inf, "-.inf": -np.inf}


def _number(v):
    """A matrix element: a number, or OpenCV's spellings of the special values ('.Nan', '-.Inf')."""
    if isinstance(v, bool):
        raise CalibrationError("an opencv-matrix holds numbers, not true/false")
    if isinstance(v, (int, float)):
        return float(v)
    if isinstance(v, str) and v.strip().lower() in _SPECIAL:
        return _SPECIAL[v.strip().lower()]
    raise CalibrationError(f"an opencv-matrix holds numbers, got {str(v)[:40]!r}")


# ------------------------------------------------------------------------------------------------ YAML
class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader and OpenCV's two matrix tags."""


def _opencv_matrix(loader, node):
    m = loader.construct_mapping(node, deep=True)
    return _matrix(m.get("rows"), m.get("cols"), m.get("dt"), m.get("data"))


_Loader.add_constructor("tag:yaml.org,2002:opencv-matrix", _opencv_matrix)


def _read_yaml(text):
    # OpenCV writes the directive as '%YAML:1.0' (YAML 1.0's form), which PyYAML refuses: drop it
    text = re.sub(r"\A%YAML[: ]1\.\d+[^\n]*\n", "", text)
    # cv2.FileStorage's APPEND mode starts a second document; OpenCV reads the documents as one map
    doc: dict = {}
    for part in yaml.load_all(text, Loader=_Loader):  # noqa: S506 (a SafeLoader subclass)
        if part is None:
            continue
        if not isinstance(part, dict):
            raise CalibrationError("its top level is not a map")
        doc.update(part)
    return doc


# ------------------------------------------------------------------------------------------------- XML
def _scalar(text):
    t = text.strip()
    if len(t) >= 2 and t[0] == t[-1] == '"':
        return t[1:-1]
    for kind in (int, float):
        try:
            return kind(t)
        except ValueError:
            pass
    return t


def _node(el, depth=0):
    if depth > 64:
        raise CalibrationError("is nested deeper than 64 levels")
    children = list(el)
    if el.get("type_id") == "opencv-matrix":
        parts = {c.tag: (c.text or "") for c in children}
        data = [_scalar(v) for v in parts.get("data", "").split()]
        return _matrix(_scalar(parts.get("rows", "")), _scalar(parts.get("cols", "")), parts.get("dt", "").strip(), data)
    if children:
        if all(c.tag == "_" for c in children):
            return [_node(c, depth + 1) for c in children]
        return {c.tag: _node(c, depth + 1) for c in children}
    tokens = (el.text or "").split()
    if len(tokens) > 1 and not (el.text or "").strip().startswith('"'):
        return [_scalar(t) for t in tokens]
    return _scalar(el.text or "")


def _read_xml(text):
    root = ET.fromstring(text)
    if root.tag != "opencv_storage":
        raise CalibrationError(f"its root element is <{root.tag}>, not <opencv_storage>")
    doc = _node(root)
    return doc if isinstance(doc, dict) else {}
