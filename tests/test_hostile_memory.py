"""Issue 26, item 6: memory is budgeted for the images too, from their headers, before decoding.

Twelve 20000x20000 PNGs (1.2 MB each on disk) with --max-memory 2G ran 166 s and ended in an
OpenCV out-of-memory traceback.  Here the PNGs are headers only (a valid IHDR, no pixel data):
nothing may decode them for the refusal to come.
"""

import json
import struct
import time
import zlib

import pytest

from organlab import load_session
from organlab.cli import main
from organlab.errors import SessionError
from organlab.preflight import IMAGE_BYTES_PER_PIXEL, check_image_memory, image_header_size


def _png_header(path, w, h):
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)  # 8-bit RGB
    chunk = b"IHDR" + ihdr
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + struct.pack(">I", len(ihdr)) + chunk + struct.pack(">I", zlib.crc32(chunk)))
    return path


def _session(root, size, n_views=12):
    (root / "views").mkdir(parents=True)
    views = []
    for i in range(n_views):
        _png_header(root / "views" / f"{i:02d}.png", 20000, 20000)
        views.append({"image": f"views/{i:02d}.png", "angle_deg": 30.0 * i,
                      "pose": {"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 500]}})
    doc = {"format": "organlab.session/1", "units": "mm", "image_size": list(size), "views": views,
           "camera": {"K": [[20000, 0, 10000], [0, 20000, 10000], [0, 0, 1]], "dist": [0, 0, 0, 0, 0]},
           "roi": {"min": [-10, -10, 0], "max": [10, 10, 20]}, "backdrop": {"color": [0, 0, 0]}}
    (root / "session.json").write_text(json.dumps(doc))
    return root


def test_image_larger_than_image_size_is_refused_from_its_header(tmp_path):
    root = _session(tmp_path / "s", (320, 240))
    t0 = time.perf_counter()
    with pytest.raises(SessionError, match=r"views\[0\]\.image: image 'views/00.png' is 20000x20000 px but image_size is 320x240"):
        load_session(root)
    assert time.perf_counter() - t0 < 5  # headers only (decoding twelve would take minutes and 14 GB)


def test_twelve_huge_views_are_refused_before_decoding(tmp_path, capsys):
    root = _session(tmp_path / "s", (20000, 20000))
    t0 = time.perf_counter()
    code = main(["reconstruct", str(root), "--out", str(tmp_path / "o"), "--max-memory", "2G", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert "12 views of 20000x20000 px" in err and "--max-memory" in err, err
    assert time.perf_counter() - t0 < 20 and not (tmp_path / "o").exists()


def test_image_memory_estimate_and_headers(tmp_path):
    assert check_image_memory((640, 480), 36, max_memory=1 << 30) == 640 * 480 * 36 * IMAGE_BYTES_PER_PIXEL
    with pytest.raises(SessionError, match="about 312.9 GiB"):  # 12 x 4e8 px x 70 B = 3.36e11 B
        check_image_memory((20000, 20000), 12, max_memory=2 << 30)
    assert image_header_size(_png_header(tmp_path / "a.png", 7, 3)) == (7, 3)
    # a JPEG: its size is in the start-of-frame segment after the others
    import cv2
    import numpy as np

    cv2.imwrite(str(tmp_path / "b.jpg"), np.zeros((11, 13, 3), np.uint8))
    assert image_header_size(tmp_path / "b.jpg") == (13, 11)
    (tmp_path / "c.png").write_bytes(b"not an image")
    assert image_header_size(tmp_path / "c.png") is None
