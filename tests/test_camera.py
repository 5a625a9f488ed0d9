import cv2
import numpy as np
import pytest

from organlab.camera import Camera, distort, rot_z, undistort


def _random_camera(rng, skew=0.0):
    fx, fy = rng.uniform(600, 900, 2)
    K = [[fx, skew * fx, rng.uniform(300, 340)], [0, fy, rng.uniform(220, 260)], [0, 0, 1]]
    dist = [-0.3, 0.12, 1.5e-3, -8e-4, -0.02]
    rvec = rng.normal(size=3) * 0.5
    R = cv2.Rodrigues(rvec)[0]
    t = rng.uniform(-50, 50, 3) + [0, 0, 500]
    return Camera(K, dist, R, t, (640, 480))


def _points_in_front(cam, rng, n=500):
    # points whose normalized coordinates stay within a plausible image (|x|, |y| < 0.5)
    xn = rng.uniform(-0.45, 0.45, (n, 2))
    z = rng.uniform(200, 900, n)
    pc = np.column_stack([xn * z[:, None], z])
    return (pc - cam.t) @ cam.R  # R.T @ (pc - t)


def test_project_matches_opencv_without_skew():
    rng = np.random.default_rng(1)
    for _ in range(5):
        cam = _random_camera(rng)
        X = _points_in_front(cam, rng)
        ours = cam.project(X)
        ref, _ = cv2.projectPoints(X, cam.rvec, cam.t, cam.K, cam.dist)
        assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-6


def test_project_by_hand_with_skew():
    # one point, every term of equations (8)-(15) written out by hand
    fx, fy, cx, cy, alpha = 800.0, 780.0, 321.0, 239.0, 0.01
    k1, k2, p1, p2, k3 = -0.3, 0.1, 0.001, -0.002, 0.01
    cam = Camera([[fx, alpha * fx, cx], [0, fy, cy], [0, 0, 1]], [k1, k2, p1, p2, k3], np.eye(3), [10.0, -20.0, 0.0])
    X = np.array([[30.0, 40.0, 200.0]])
    x, y = (30 + 10) / 200, (40 - 20) / 200  # 0.2, 0.1
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    u = fx * (xd + alpha * yd) + cx
    v = fy * yd + cy
    np.testing.assert_allclose(cam.project(X)[0], [u, v], atol=1e-9)
    # and the skew really moves u: the same camera without skew differs by fx*alpha*yd
    cam0 = Camera([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], cam.dist, cam.R, cam.t)
    assert cam.project(X)[0, 0] - cam0.project(X)[0, 0] == pytest.approx(fx * alpha * yd, abs=1e-9)


def test_points_behind_camera_are_nan():
    cam = Camera(np.diag([800.0, 800, 1]) + [[0, 0, 320], [0, 0, 240], [0, 0, 0]], None)
    uv, z = cam.project([[0, 0, -10.0], [0, 0, 0.0], [1, 1, 10.0]], return_depth=True)
    assert np.isnan(uv[:2]).all() and np.isfinite(uv[2]).all()
    np.testing.assert_allclose(z, [-10, 0, 10])


def test_undistort_inverts_distort():
    rng = np.random.default_rng(2)
    xn = rng.uniform(-0.5, 0.5, (1000, 2))
    dist = np.array([-0.3, 0.12, 1.5e-3, -8e-4, -0.02])
    back = undistort(distort(xn, dist), dist)
    assert np.abs(back - xn).max() < 1e-10


def test_rays_hit_the_projected_points():
    rng = np.random.default_rng(3)
    cam = _random_camera(rng, skew=0.02)
    X = _points_in_front(cam, rng, 200)
    o, d = cam.rays(cam.project(X))
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    # distance of each point from its ray
    v = X - o
    off = v - (v * d).sum(1)[:, None] * d
    assert np.linalg.norm(off, axis=1).max() < 1e-6
    np.testing.assert_allclose(o[0], cam.center)


def test_table_angle_pose():
    rng = np.random.default_rng(4)
    cam = _random_camera(rng)
    X = rng.uniform(-50, 50, (20, 3))
    # a point fixed on the table at X is at Rz(a) X at angle a: both must project alike
    a = 37.0
    np.testing.assert_allclose(cam.at_table_angle(a).project(X), cam.project(X @ rot_z(a).T), atol=1e-9)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(K=np.eye(2)), "K must"),
        (dict(K=[[-800, 0, 320], [0, 800, 240], [0, 0, 1]]), "positive focal"),
        (dict(dist=[0.1, 0.2]), "5 coefficients"),
        (dict(R=np.ones((3, 3))), "rotation"),
        (dict(t=[1, 2]), "3 elements"),
        (dict(image_size=(0, 480)), "image_size"),
    ],
)
def test_camera_validation(kwargs, match):
    base = dict(K=[[800, 0, 320], [0, 800, 240], [0, 0, 1]], dist=None, R=None, t=None, image_size=(640, 480))
    base.update(kwargs)
    with pytest.raises(ValueError, match=match):
        Camera(**base)


def test_camera_is_immutable_and_roundtrips():
    cam = _random_camera(np.random.default_rng(5), skew=0.01)
    with pytest.raises(ValueError):
        cam.K[0, 0] = 1.0
    back = Camera.from_dict(cam.to_dict())
    X = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(back.project(X), cam.project(X))
