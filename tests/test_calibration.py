"""Calibration: board detection and orientation, intrinsic and turntable fits, IO, session end to end."""

import json

import cv2
import numpy as np
import pytest

from organlab import calibration as calibio
from organlab import synthetic as S
from organlab.calibration import (
    Calibration,
    board_points,
    calibrate,
    calibrate_intrinsics,
    calibrate_turntable,
    detect_board,
    fit_intrinsics,
    fit_turntable,
)
from organlab.figures import check_figures
from organlab.camera import Camera, rot_z
from organlab.errors import CalibrationError
from organlab.session import Pattern, load_session

PAT = Pattern((9, 6), 20.0)
ANGLES = [0.0, 60.0, 120.0, 180.0, 240.0, 300.0]


# ----------------------------------------------------------------- helpers
def _board_texture(pattern, px_per_mm, margin=15.0):
    """Flat board image (board frame, mm -> px) with the session-format colour rule."""
    nx, ny = pattern.inner_corners
    s = pattern.square_size
    x0, y0 = -s - margin, -s - margin
    w = int(round((nx * s + margin - x0) * px_per_mm))
    h = int(round((ny * s + margin - y0) * px_per_mm))
    v, u = np.mgrid[0:h, 0:w]
    x = (u + 0.5) / px_per_mm + x0
    y = (v + 0.5) / px_per_mm + y0
    a = np.floor(x / s).astype(int) + 1
    b = np.floor(y / s).astype(int) + 1
    inside = (a >= 0) & (a <= nx) & (b >= 0) & (b <= ny)
    img = np.where(inside & ((a + b) % 2 == 0), 30, 215).astype(np.uint8)
    # texture pixel (u, v) -> board (x, y): x = (u + 0.5) / ppm + x0
    T = np.array([[1 / px_per_mm, 0, x0 + 0.5 / px_per_mm], [0, 1 / px_per_mm, y0 + 0.5 / px_per_mm], [0, 0, 1]])
    return img, T


def _warp_board(K, R, t, pattern, size, up=4):
    """Pinhole (no distortion) image of the board at board-to-camera pose (R, t)."""
    tex, T = _board_texture(pattern, px_per_mm=6.0)
    S_up = np.diag([up, up, 1.0])
    S_up[0, 2] = S_up[1, 2] = (up - 1) / 2  # pixel centres
    H = S_up @ K @ np.column_stack([R[:, 0], R[:, 1], t]) @ T
    big = cv2.warpPerspective(tex, H, (size[0] * up, size[1] * up), flags=cv2.INTER_LINEAR, borderValue=90)
    return cv2.resize(big, size, interpolation=cv2.INTER_AREA)


def _face_pose(roll_deg, tilt_deg=0.0, dist=420.0):
    """Board facing the camera (printed side toward it), rolled in-plane, centred on the optical axis."""
    R_face = np.diag([1.0, -1.0, -1.0])
    tilt = cv2.Rodrigues(np.array([np.deg2rad(tilt_deg), 0.0, 0.0]))[0]
    R = tilt @ R_face @ rot_z(roll_deg)
    centre = np.array([80.0, 50.0, 0.0])
    t = np.array([0.0, 0.0, dist]) - R @ centre
    return R, t


def _intrinsic_corners(camera, n, noise_px, seed, skew=0.0):
    cam0 = camera.with_pose(np.eye(3), np.zeros(3))
    if skew:
        K = cam0.K.copy()
        K[0, 1] = skew * K[0, 0]
        cam0 = Camera(K, cam0.dist, image_size=cam0.image_size)
    rng = np.random.default_rng(seed)
    obj = board_points(PAT)
    out = {}
    for k, (R, t) in enumerate(S.intrinsic_board_poses(camera, n, seed=seed)):
        out[f"i{k}"] = cam0.project(obj @ R.T + t) + rng.normal(0, noise_px, (obj.shape[0], 2))
    return out, cam0


def _turntable_corners(camera, angles, noise_px, seed):
    rng = np.random.default_rng(seed)
    out = {}
    for k, a in enumerate(angles):
        X = S.turntable_board_points(a, PAT)
        # X is where the table carries the board at angle a; the camera at angle 0 sees it
        out[f"t{k}"] = camera.project(X) + rng.normal(0, noise_px, (X.shape[0], 2))
    return out


# ------------------------------------------------------------ board order
def test_board_points_layout():
    P = board_points(PAT)
    assert P.shape == (54, 3)
    np.testing.assert_allclose(P[1] - P[0], [20, 0, 0])
    np.testing.assert_allclose(P[9] - P[0], [0, 20, 0])
    np.testing.assert_allclose(P[-1], [160, 100, 0])


@pytest.mark.parametrize("roll", [0.0, 90.0, 180.0, 270.0, 37.0, -143.0])
def test_detect_board_orientation_rule(roll):
    """Whatever the board's in-plane rotation (a detector may flip it), corners come in board order."""
    K = np.array([[700.0, 0, 319.5], [0, 700.0, 239.5], [0, 0, 1]])
    R, t = _face_pose(roll, tilt_deg=25.0)
    img = _warp_board(K, R, t, PAT, (640, 480))
    truth = Camera(K, None, image_size=(640, 480)).project(board_points(PAT) @ R.T + t)
    corners = detect_board(img, PAT, require_orientation=True)
    assert corners is not None and corners.shape == (54, 2) and corners.dtype == np.float64
    np.testing.assert_allclose(corners, truth, atol=0.25)


def test_detect_board_colour_image_and_none():
    K = np.array([[700.0, 0, 319.5], [0, 700.0, 239.5], [0, 0, 1]])
    R, t = _face_pose(180.0)
    grey = _warp_board(K, R, t, PAT, (640, 480))
    rgb = np.repeat(grey[:, :, None], 3, axis=2)
    np.testing.assert_allclose(detect_board(rgb, PAT), detect_board(grey, PAT))
    assert detect_board(np.full((480, 640), 128, np.uint8), PAT) is None
    # wrong pattern size: not found
    assert detect_board(grey, Pattern((8, 6), 20.0)) is None


def test_detect_board_repeated_image():
    """A second detection of the same pixels (served by the per-process cache) equals the first, is not
    the caller's array, and another image or board size is detected afresh."""
    from organlab.calibration import _board

    K = np.array([[700.0, 0, 319.5], [0, 700.0, 239.5], [0, 0, 1]])
    imgs, truths = [], []
    for roll in (20.0, 200.0):  # the same board turned half a turn: its corners come in board order both times
        R, t = _face_pose(roll, tilt_deg=20.0)
        imgs.append(_warp_board(K, R, t, PAT, (640, 480)))
        truths.append(Camera(K, None, image_size=(640, 480)).project(board_points(PAT) @ R.T + t))
    _board._cache.clear()
    first = detect_board(imgs[0], PAT)
    first_copy = first.copy()
    first[:] = -1.0  # the caller may change what it got
    again = detect_board(imgs[0].copy(), PAT)  # same pixels, other array
    np.testing.assert_array_equal(again, first_copy)
    np.testing.assert_allclose(again, truths[0], atol=0.25)
    other = detect_board(imgs[1], PAT)
    np.testing.assert_allclose(other, truths[1], atol=0.25)
    assert np.abs(other - again).max() > 10  # not the first image's corners
    assert detect_board(imgs[0], Pattern((8, 6), 20.0)) is None  # the board size is part of the key


def test_detections_kept_across_processes(tmp_path, monkeypatch):
    """ORGANLAB_DETECTION_CACHE: a detection is written once and read back by a process that has not seen
    the image (here: the process cache emptied and the detector made to fail), identical; a damaged file or
    another detector's code is measured again."""
    from organlab.calibration import _board

    K = np.array([[700.0, 0, 319.5], [0, 700.0, 239.5], [0, 0, 1]])
    R, t = _face_pose(35.0, tilt_deg=15.0)
    img = _warp_board(K, R, t, PAT, (640, 480))
    truth = Camera(K, None, image_size=(640, 480)).project(board_points(PAT) @ R.T + t)
    folder = tmp_path / "detections"
    monkeypatch.setenv(_board.DETECTION_CACHE_ENV, str(folder))
    monkeypatch.setattr(_board, "_cache", type(_board._cache)())
    first = detect_board(img, PAT, require_orientation=True)
    np.testing.assert_allclose(first, truth, atol=0.25)
    blank = np.full((480, 640), 128, np.uint8)
    assert detect_board(blank, PAT) is None  # "no board" is kept too
    files = sorted(folder.glob("*.npz"))
    assert len(files) == 2 and not list(folder.glob(".*"))  # no temporary file left

    def fail(*a):
        raise AssertionError("measured again")

    real = _board._find_corners
    monkeypatch.setattr(_board, "_find_corners", fail)
    _board._cache.clear()
    np.testing.assert_array_equal(detect_board(img, PAT, require_orientation=True), first)
    assert detect_board(blank, PAT) is None
    # a half-written file (a process killed before its rename leaves only the temporary one; a damaged
    # one is read as absent) and another version of the detector's code: measured again
    monkeypatch.setattr(_board, "_find_corners", real)
    _board._cache.clear()
    mine = next(f for f in files if f.stat().st_size > 600)  # the board's (54 corners), not the blank's
    mine.write_bytes(mine.read_bytes()[:100])
    np.testing.assert_array_equal(detect_board(img, PAT, require_orientation=True), first)
    assert mine.stat().st_size > 600  # written again, whole
    monkeypatch.setattr(_board, "_code_digest", "0" * 16)
    monkeypatch.setattr(_board, "_find_corners", fail)
    _board._cache.clear()
    with pytest.raises(AssertionError, match="measured again"):
        detect_board(img, PAT)
    # unset: nothing read or written
    monkeypatch.delenv(_board.DETECTION_CACHE_ENV)
    monkeypatch.setattr(_board, "_find_corners", real)
    _board._cache.clear()
    n = len(list(folder.iterdir()))
    np.testing.assert_array_equal(detect_board(img, PAT, require_orientation=True), first)
    assert len(list(folder.iterdir())) == n


# ------------------------------------------------------------- intrinsics
def test_fit_intrinsics_accuracy_and_uncertainty():
    truth = S.default_camera()
    corners, cam0 = _intrinsic_corners(truth, 8, 0.1, seed=3)
    res = fit_intrinsics(corners, PAT, image_size=truth.image_size)
    K, Kt = res.camera.K, cam0.K
    assert abs(K[0, 0] / Kt[0, 0] - 1) < 0.002 and abs(K[1, 1] / Kt[1, 1] - 1) < 0.002
    assert np.all(np.abs(K[:2, 2] - Kt[:2, 2]) < 1.5)
    assert 0.05 < res.rms_px < 0.2  # noise 0.1 px per coordinate -> ~0.14 px
    # the stated 3-sigma uncertainty covers the truth
    u = res.uncertainty
    assert np.all(np.abs([K[0, 0] - Kt[0, 0], K[1, 1] - Kt[1, 1]]) < u["fc"])
    assert np.all(np.abs(K[:2, 2] - Kt[:2, 2]) < u["cc"])
    assert np.all(np.abs(res.camera.dist[:4] - cam0.dist[:4]) < u["kc"][:4])
    assert u["kc"][4] == 0 and "k3" in res.fixed and "alpha_c" in res.fixed
    assert set(res.per_image_rms) == set(corners) and not res.rejected
    d = res.to_dict()
    json.dumps(d)
    assert d["rms_px"] == res.rms_px and len(d["images"]) == 8


def test_fit_intrinsics_rejects_bad_image():
    truth = S.default_camera()
    corners, cam0 = _intrinsic_corners(truth, 9, 0.1, seed=4)
    rng = np.random.default_rng(0)
    corners["i5"] = corners["i5"] + rng.normal(0, 3.0, corners["i5"].shape)
    res = fit_intrinsics(corners, PAT, image_size=truth.image_size)
    assert list(res.rejected) == ["i5"] and "RMS" in res.rejected["i5"]
    assert "i5" not in res.per_image_rms and res.rms_px < 0.2
    assert abs(res.camera.K[0, 0] / cam0.K[0, 0] - 1) < 0.002


def test_fit_intrinsics_estimates_skew():
    truth = S.default_camera()
    corners, cam0 = _intrinsic_corners(truth, 10, 0.05, seed=5, skew=0.004)
    res = fit_intrinsics(corners, PAT, image_size=truth.image_size, estimate_skew=True)
    assert "alpha_c" not in res.fixed and res.std["alpha_c"] > 0
    assert abs(res.camera.skew - 0.004) < max(res.uncertainty["alpha_c"], 1e-4)
    held = fit_intrinsics(corners, PAT, image_size=truth.image_size)
    assert held.camera.skew == 0 and held.rms_px > res.rms_px


# -------------------------------------------------------------- turntable
def test_fit_turntable_joint_least_squares():
    truth = S.default_camera()
    corners = _turntable_corners(truth, ANGLES, 0.1, seed=6)
    tt = fit_turntable(corners, dict(zip(corners, ANGLES)), truth, PAT)
    assert tt.rms_px < 0.2 and not tt.flagged
    for a in np.arange(0, 360, 15):
        assert np.linalg.norm(tt.view_camera(a).center - truth.at_table_angle(a).center) < 1.0
    np.testing.assert_allclose(tt.R_cam, truth.R, atol=2e-4)
    # the board's first corner at angle 0: BOARD_CENTER_XY minus half the board
    R_b, t_b = S.turntable_board_pose(PAT)
    np.testing.assert_allclose(tt.board_offset_mm, t_b[:2], atol=0.2)
    np.testing.assert_allclose(tt.axis_direction_cam, truth.R[:, 2], atol=2e-4)
    assert np.all(tt.std["camera_center_mm"] > 0) and np.all(tt.std["camera_center_mm"] < 1.0)
    d = tt.to_dict()
    json.dumps(d)
    assert d["axis"]["camera_distance_to_axis_mm"] == pytest.approx(505.0, abs=1.0)


def test_fit_turntable_flags_moved_board():
    truth = S.default_camera()
    angles = ANGLES + [30.0, 90.0]
    corners = _turntable_corners(truth, angles, 0.1, seed=7)
    # the board slid 4 mm along the table before image t3
    X = S.turntable_board_points(angles[3], PAT) + [4.0, 0.0, 0.0]
    corners["t3"] = truth.project(X)
    tt = fit_turntable(corners, dict(zip(corners, angles)), truth, PAT)
    assert tt.flagged == ["t3"]
    assert tt.per_image_rms["t3"] > 5 * max(v for k, v in tt.per_image_rms.items() if k != "t3")
    assert tt.rms_px < 0.2
    assert np.linalg.norm(tt.camera.center - truth.center) < 1.0


def _blank_images(n, size=(320, 240)):
    return [np.full((size[1], size[0]), 120, np.uint8) for _ in range(n)]


def test_turntable_bad_input():
    cam = S.default_camera((320, 240))
    imgs = _blank_images(3)
    with pytest.raises(CalibrationError, match="angle"):
        calibrate_turntable(imgs, [0.0, float("nan"), 20.0], cam, PAT)
    with pytest.raises(CalibrationError, match="angles"):
        calibrate_turntable(imgs, [0.0, 10.0], cam, PAT)
    with pytest.raises(CalibrationError, match="missing"):
        calibrate_turntable(imgs, None, cam, PAT)
    with pytest.raises(CalibrationError, match="odd number"):
        calibrate_turntable(imgs, [0, 1, 2], cam, Pattern((8, 6), 20.0))
    with pytest.raises(CalibrationError, match="inner_corners"):
        calibrate_turntable(imgs, [0, 1, 2], cam, PAT)
    with pytest.raises(CalibrationError, match="same size"):
        calibrate_turntable(imgs + _blank_images(1, (640, 480)), [0, 1, 2, 3], cam, PAT)


def test_intrinsics_bad_input():
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    good = [_warp_board(K, *_face_pose(r, tilt_deg=20.0), PAT, (640, 480)) for r in (0.0, 30.0)]
    blank = _blank_images(2, (640, 480))
    with pytest.raises(CalibrationError, match="inner_corners"):
        calibrate_intrinsics(blank, PAT, image_size=(640, 480))
    with pytest.raises(CalibrationError, match=r"only 2 of 4 .*b0 \(no 9x6 board found\)"):
        calibrate_intrinsics(good + blank, PAT, image_size=(640, 480), names=["g0", "g1", "b0", "b1"])
    with pytest.raises(CalibrationError, match="same size"):
        calibrate_intrinsics(good + _blank_images(1), PAT, image_size=(640, 480))


# ------------------------------------------------------------------- IO
def test_bouguet_roundtrip(tmp_path):
    K = np.array([[657.46, 0.0, 303.14], [0.0, 657.95, 242.57], [0.0, 0.0, 1.0]])
    K[0, 1] = 0.001 * K[0, 0]
    cam = Camera(K, [-0.254, 0.1214, -2.1e-4, 2.0e-5, 0.0], image_size=(640, 480))
    err = {"fc_error": [0.40, 0.43], "cc_error": [0.81, 0.74], "alpha_c_error": 0.0002, "kc_error": [3e-3, 1.2e-2, 1.7e-4, 1.7e-4, 0]}
    p = calibio.write_bouguet(tmp_path / "Calib_Results.m", cam, errors=err)
    back, e = calibio.read_bouguet(p)
    np.testing.assert_allclose(back.K, cam.K, rtol=1e-12)
    np.testing.assert_allclose(back.dist, cam.dist, atol=1e-14)
    assert back.image_size == (640, 480)
    np.testing.assert_allclose(e["kc_error"], err["kc_error"])
    assert e["alpha_c_error"] == pytest.approx(0.0002)


def test_read_bouguet_toolbox_layout(tmp_path):
    """The toolbox's Calib_Results.m: comments, KK as an expression, 4 kc, extrinsics, no errors for some."""
    text = """% Intrinsic and Extrinsic Camera Parameters
%
% This script file can be directly excecuted under Matlab to recover the camera intrinsic and extrinsic parameters.
%-- Focal length:
fc = [ 657.303458404999950 ; 657.744664647899900 ];

%-- Principal point:
cc = [ 302.717127397299980 ; 242.334218212600020 ];

%-- Skew coefficient:
alpha_c = 0.000000000000000;

%-- Distortion coefficients:
kc = [ -0.256113702563000 ; 0.128133428802000 ; -0.000202611006120 ; 0.000041036245566 ];

%-- Focal length uncertainty:
fc_error = [ 0.354889800389700 ; 0.381179402600700 ];

%-- Image size:
nx = 640;
ny = 480;

%-- Various other variables (may be ignored if you do not use the Matlab Calibration Toolbox):
KK = [fc(1) alpha_c*fc(1) cc(1);0 fc(2) cc(2) ; 0 0 1];
n_ima = 20;
omc_1 = [ 1.654 ; 1.655 ; -0.672 ];
Tc_1  = [ -211.0 ; -97.6 ; 1165.6 ];
"""
    p = tmp_path / "Calib_Results.m"
    p.write_text(text)
    cam, err = calibio.read_bouguet(p)
    assert cam.K[0, 0] == pytest.approx(657.303458405) and cam.K[1, 2] == pytest.approx(242.3342182126)
    np.testing.assert_allclose(cam.dist, [-0.256113702563, 0.128133428802, -0.00020261100612, 0.000041036245566, 0.0])
    assert cam.image_size == (640, 480) and set(err) == {"fc_error"}
    assert calibio.read_camera(p).K[0, 0] == cam.K[0, 0]
    bad = tmp_path / "bad.m"
    bad.write_text("nx = 640;\n")
    with pytest.raises(CalibrationError, match="fc"):
        calibio.read_bouguet(bad)


@pytest.mark.parametrize("suffix", [".yml", ".xml"])
def test_opencv_roundtrip(tmp_path, suffix):
    cam = S.default_camera()
    p = calibio.write_opencv(tmp_path / f"camera{suffix}", cam, rms_px=0.123)
    back, extra = calibio.read_opencv(p)
    np.testing.assert_allclose(back.K, cam.K, rtol=1e-12)
    np.testing.assert_allclose(back.dist, cam.dist, rtol=1e-12)
    assert back.image_size == cam.image_size and extra["avg_reprojection_error"] == pytest.approx(0.123)
    assert calibio.read_camera(p).K[0, 2] == cam.K[0, 2]


def test_opencv_rejects_rational_model(tmp_path):
    p = tmp_path / "c.yml"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[-0.2, 0.1, 0, 0, 0, 0.3, 0, 0]]).T)
    fs.release()
    with pytest.raises(CalibrationError, match="beyond k3"):
        calibio.read_opencv(p)


# ------------------------------------------------- rendered session (slow)
N_INTR = 12


@pytest.fixture(scope="module")
def rendered_session(tmp_path_factory):
    """A calibration session rendered through the full camera model (thesis distortion k1 = -0.3)."""
    root = tmp_path_factory.mktemp("calsession")
    truth = S.default_camera()
    cam0 = truth.with_pose(np.eye(3), np.zeros(3))
    (root / "intr").mkdir()
    (root / "tt").mkdir()
    intr = []
    for k, (R, t) in enumerate(S.intrinsic_board_poses(truth, N_INTR, seed=0)):
        img = S.render_board(cam0, R, t, PAT, table=False, supersample=2, noise_sigma=1.0, seed=[0, k])
        cv2.imwrite(str(root / "intr" / f"{k:02d}.png"), img)
        intr.append(f"intr/{k:02d}.png")
    R_b, t_b = S.turntable_board_pose(PAT)
    tt = []
    for k, a in enumerate(ANGLES):
        img = S.render_board(truth.at_table_angle(a), R_b, t_b, PAT, supersample=2, noise_sigma=1.0, seed=[1, k])
        cv2.imwrite(str(root / "tt" / f"{k:03d}.png"), img)
        tt.append({"image": f"tt/{k:03d}.png", "angle_deg": a})
    session = {
        "format": "organlab.session/1",
        "units": "mm",
        "image_size": list(truth.image_size),
        "pattern": {"inner_corners": [9, 6], "square_size": 20.0},
        "calibration": {"intrinsic_images": intr, "turntable_images": tt},
        "views": [],
        "roi": {"min": [-70, -70, 0.5], "max": [70, 70, 200]},
    }
    (root / "session.json").write_text(json.dumps(session))
    return root, truth


@pytest.mark.slow
def test_calibrate_session_rendered(rendered_session, tmp_path):
    root, truth = rendered_session
    session = load_session(root)
    calls = []
    cal = calibrate(session, progress=lambda d, n: calls.append((d, n)))
    assert calls[-1] == (N_INTR + 6, N_INTR + 6)
    K, Kt = cal.camera.K, truth.K
    # the issue asks focal within 0.2 % and cc within 1.5 px; we hold half of that
    # (measured: focal -0.02 %, cc (-0.22, 0.13) px)
    assert abs(K[0, 0] / Kt[0, 0] - 1) < 0.001 and abs(K[1, 1] / Kt[1, 1] - 1) < 0.001
    assert np.all(np.abs(K[:2, 2] - Kt[:2, 2]) < 0.75)
    assert cal.rms_px < 0.2 and not cal.intrinsics.rejected
    u = cal.intrinsics.uncertainty
    assert np.all(np.abs(np.diag(K)[:2] - np.diag(Kt)[:2]) < u["fc"])
    assert np.all(np.abs(K[:2, 2] - Kt[:2, 2]) < u["cc"])
    tt = cal.turntable
    assert tt.rms_px < 0.2 and not tt.flagged and not tt.rejected
    for a in np.arange(0, 360, 20):
        c = tt.camera.at_table_angle(a).center
        assert np.linalg.norm(c - truth.at_table_angle(a).center) < 1.0
    assert not (root / "calibration.json").exists()  # calibrate writes nothing by itself

    path = cal.save(tmp_path / "calibration.json")
    again = Calibration.load(path)
    assert again.mismatch(session) == []
    np.testing.assert_allclose(again.turntable.camera.R, tt.camera.R)
    np.testing.assert_allclose(again.camera.K, K)
    for a, b in zip(again.cameras(session), cal.cameras(session)):
        np.testing.assert_allclose(a.t, b.t)
    assert again.intrinsics.per_image_rms == cal.intrinsics.per_image_rms
    np.testing.assert_allclose(again.intrinsics.uncertainty["fc"], u["fc"])
    # calibration.json keeps each image's detected corners: the figures draw them without detecting again
    saved = json.loads(path.read_text())
    for entries in (saved["camera"]["images"], saved["turntable"]["images"]):
        for name, e in entries.items():
            corners = np.asarray(e["corners_px"])
            assert corners.shape == (54, 2)
            truth_cam = truth.at_table_angle(e["angle_deg"]) if "angle_deg" in e else None
            if truth_cam is not None:  # turntable image: the corners are where the true camera sees the board
                R_b, t_b = S.turntable_board_pose(PAT)
                uv = truth_cam.project(S.board_object_points(PAT) @ R_b.T + t_b)
                assert np.sqrt(((corners - uv) ** 2).sum(1).mean()) < 0.2

    figs = check_figures(session, again, tmp_path / "figs")
    assert len(figs) == N_INTR + 6 and all(f.is_file() for f in figs)
    fig = cv2.imread(str(figs[-1]))
    assert fig.shape[:2] == (2 * truth.height, 2 * truth.width)
    # red reprojection circles, green detection crosses, yellow axis all drawn
    b, g, r = fig[..., 0].astype(int), fig[..., 1].astype(int), fig[..., 2].astype(int)
    assert np.sum((r > 200) & (g < 100) & (b < 100)) > 500
    assert np.sum((g > 180) & (r < 100) & (b < 100)) > 500
    assert np.sum((r > 200) & (g > 180) & (b < 60)) > 100


@pytest.mark.slow
def test_calibrate_session_given_camera(rendered_session, tmp_path):
    root, truth = rendered_session
    sj = json.loads((root / "session.json").read_text())
    sj["camera"] = {"K": truth.K.tolist(), "dist": truth.dist.tolist()}
    sub = root / "given"
    sub.mkdir(exist_ok=True)
    sj["calibration"]["turntable_images"] = [{**e, "image": "../" + e["image"]} for e in sj["calibration"]["turntable_images"]]
    sj["calibration"]["intrinsic_images"] = []
    (sub / "session.json").write_text(json.dumps(sj))
    cal = calibrate(load_session(sub, allow_outside_paths=True))  # its images are in the folder above
    assert cal.intrinsics is None and cal.rms_px is None
    np.testing.assert_allclose(cal.camera.K, truth.K)
    assert np.linalg.norm(cal.turntable.camera.center - truth.center) < 0.5
    d = json.loads(cal.save(tmp_path / "c.json").read_text())
    assert d["camera"]["source"] == "session.json" and d["camera"]["rms_px"] is None
    assert Calibration.load(tmp_path / "c.json").intrinsics is None


@pytest.mark.slow
def test_rendered_corners_match_truth(rendered_session):
    """Detected corners of the distorted, tilted rendered boards against their true projections."""
    root, truth = rendered_session
    cam0 = truth.with_pose(np.eye(3), np.zeros(3))
    errs = []
    for k, (R, t) in enumerate(S.intrinsic_board_poses(truth, N_INTR, seed=0)):
        c = detect_board(cv2.imread(str(root / "intr" / f"{k:02d}.png"), cv2.IMREAD_GRAYSCALE), PAT)
        uv = cam0.project(S.board_object_points(PAT) @ R.T + t)
        errs.append(np.sqrt(np.mean(np.sum((c - uv) ** 2, axis=1))))
    # measured: mean 0.047 px, worst 0.12 px (cornerSubPix alone: 0.10 and 0.21 px)
    assert np.mean(errs) < 0.07 and np.max(errs) < 0.16
