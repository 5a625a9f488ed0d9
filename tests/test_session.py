import json

import cv2
import numpy as np
import pytest

from organlab import load_session
from organlab.errors import SessionError

W, H = 64, 48


def _write(path, img):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), img)


def _make(tmp_path, **changes):
    """A tiny valid session (given camera, poses, masks); ``changes`` edits session.json."""
    root = tmp_path / "s"
    img = np.full((H, W, 3), 40, np.uint8)
    _write(root / "views/000.png", img)
    _write(root / "views/010.png", img)
    _write(root / "masks/000.png", np.zeros((H, W), np.uint8))
    _write(root / "background/00.png", img)
    _write(root / "calibration/turntable/000.png", img[:, :, 0])
    doc = {
        "format": "organlab.session/1",
        "name": "tiny",
        "units": "mm",
        "image_size": [W, H],
        "pattern": {"type": "checkerboard", "inner_corners": [9, 6], "square_size": 20.0},
        "camera": {"K": [[80, 0, 32], [0, 80, 24], [0, 0, 1]], "dist": [0, 0, 0, 0, 0]},
        "calibration": {"turntable_images": [{"image": "calibration/turntable/000.png", "angle_deg": 0}]},
        "background_images": ["background/00.png"],
        "views": [
            {"image": "views/000.png", "angle_deg": 0, "mask": "masks/000.png",
             "pose": {"R": np.eye(3).tolist(), "t": [0, 0, 500]}},
            {"image": "views/010.png", "angle_deg": 10},
        ],
        "roi": {"min": [-10, -10, 0], "max": [10, 10, 20]},
        "reference": {"volume_mm3": 1000},
    }
    for key, value in changes.items():
        target = doc
        *parents, last = key.split(".")
        for p in parents:
            target = target[int(p)] if isinstance(target, list) else target[p]
        if value is _DELETE:
            del target[int(last) if isinstance(target, list) else last]
        else:
            target[int(last) if isinstance(target, list) else last] = value
    (root / "session.json").write_text(json.dumps(doc))
    return root


_DELETE = object()


def test_valid_session_loads(tmp_path):
    s = load_session(_make(tmp_path))
    assert s.image_size == (W, H)
    assert len(s.views) == 2 and s.views[0].pose is not None and s.views[1].pose is None
    assert s.views[0].mask.name == "000.png"
    assert s.reference["volume_mm3"] == 1000
    np.testing.assert_allclose(s.views[0].pose[1], [0, 0, 500])
    assert s.turntable_images[0][1] == 0.0


def test_calibration_only_session_is_valid(tmp_path):
    s = load_session(_make(tmp_path, views=[]))
    assert s.views == ()


@pytest.mark.parametrize(
    "changes, match",
    [
        ({"format": "organlab.session/2"}, r"format: must be exactly"),
        ({"units": "cm"}, r"units"),
        ({"image_size": [64]}, r"image_size"),
        ({"roi.min": [0, -10, 0], "roi.max": [0, 10, 20]}, r"roi: min must be < max on every axis; not on x"),
        ({"roi.max": [10, 10, -1]}, r"not on z"),
        ({"views.1.image": "views/missing.png"}, r"views\[1\]\.image: image 'views/missing.png' does not exist"),
        ({"views.1.angle_deg": _DELETE}, r"views\[1\]\.angle_deg: is missing"),
        ({"views.0.pose": {"R": np.eye(3).tolist(), "t": [0, 0]}}, r"views\[0\]\.pose\.t"),
        ({"views.0.pose": {"R": (2 * np.eye(3)).tolist(), "t": [0, 0, 1]}}, r"views\[0\]\.pose\.R: is not a rotation"),
        ({"calibration.turntable_images": []}, r"views\[1\]\.pose: this view has no pose and the session has no turntable calibration"),
        ({"calibration.turntable_images.0.angle_deg": _DELETE}, r"turntable_images\[0\]\.angle_deg"),
        ({"camera.K": [[1, 2], [3, 4]]}, r"camera\.K"),
        ({"camera": _DELETE}, r"camera: no intrinsics"),
        ({"background_images": []}, r"background_images: views without 'mask'"),
        ({"pattern": _DELETE}, r"pattern: is required"),
        ({"pattern.inner_corners": [9]}, r"pattern\.inner_corners"),
        ({"reference.volume_mm3": -3}, r"reference\.volume_mm3"),
        ({"views": "x"}, r"views: is required"),
    ],
)
def test_bad_session_json(tmp_path, changes, match):
    root = _make(tmp_path, **changes)
    with pytest.raises(SessionError, match=match) as info:
        load_session(root)
    assert "session.json" in str(info.value)
    assert "\n" not in str(info.value)


def test_bad_json_syntax(tmp_path):
    root = _make(tmp_path)
    (root / "session.json").write_text('{"format": "organlab.session/1",\n "units": mm}')
    with pytest.raises(SessionError, match=r"session.json: invalid JSON at line 2 column"):
        load_session(root)


def test_missing_folder_and_file(tmp_path):
    with pytest.raises(SessionError, match="does not exist"):
        load_session(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SessionError, match="no session.json"):
        load_session(tmp_path / "empty")


def test_corrupt_image(tmp_path):
    root = _make(tmp_path)
    (root / "views/010.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(SessionError, match=r"views\[1\]\.image: image 'views/010.png' cannot be read"):
        load_session(root)


def test_wrong_image_size(tmp_path):
    root = _make(tmp_path)
    _write(root / "background/00.png", np.zeros((H + 1, W, 3), np.uint8))
    with pytest.raises(SessionError, match=r"background_images\[0\]: image 'background/00.png' is 64x49 px but image_size is 64x48"):
        load_session(root)


def test_bad_calibration_json(tmp_path):
    root = _make(tmp_path)
    (root / "calibration.json").write_text("{not json")
    with pytest.raises(SessionError, match=r"calibration.json: invalid JSON.*organlab calibrate"):
        load_session(root)


def test_unknown_keys_are_ignored(tmp_path):
    s = load_session(_make(tmp_path, operator="jane", lighting={"lux": 300}))
    assert s.name == "tiny"
