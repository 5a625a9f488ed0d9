"""The same input gives the same bits: the intrinsic fit, and through it every later stage.

OpenCV's ``calibrateCameraExtended`` on its threads summed in another order from call to call: the same
corners gave six different calibrations in six calls (about 1e-10 relative apart), so the cameras, the hull
field (1 ulp) and the finished mesh (up to 5e-4 mm) of two runs of ``organlab reconstruct`` on the same session
differed.  :func:`organlab.calibration.fit_intrinsics` runs it on one thread.
"""

import hashlib

import cv2
import numpy as np

from organlab import synthetic as S
from organlab.calibration import board_points, fit_intrinsics
from organlab.camera import rot_z
from organlab.session import Pattern

PAT = Pattern((9, 6), 20.0)


def _corners(n=12, seed=5):
    truth = S.default_camera()
    rng = np.random.default_rng(seed)
    obj = board_points(PAT)
    centre = obj.mean(axis=0)
    corners = {}
    for i in range(n):
        rx, ry = np.radians(rng.uniform(-35, 35, 2))
        R = (cv2.Rodrigues(np.array([rx, ry, 0.0]))[0] @ rot_z(rng.uniform(-30, 30)))
        t = np.array([0.0, 0.0, rng.uniform(350, 500)]) - R @ centre + np.r_[rng.uniform(-40, 40, 2), 0.0]
        px, _ = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t, truth.K, truth.dist)
        corners[f"board{i:02d}.png"] = px.reshape(-1, 2) + rng.normal(0, 0.15, (len(obj), 2))
    return corners, truth


def _bits(res):
    c = res.camera
    return hashlib.sha1(np.concatenate([c.K.ravel(), c.dist, *[np.ravel(v) for e in res.extrinsics.values() for v in e]])
                        .tobytes()).hexdigest()


def test_intrinsic_fit_gives_the_same_bits_every_call():
    corners, truth = _corners()
    threads = cv2.getNumThreads()
    fits = [fit_intrinsics(corners, PAT, image_size=truth.image_size) for _ in range(6)]
    # a fit that could be wrong: the focal length within 0.5 % of the camera that made the corners (measured 0.30 %: 12 boards, 0.15 px noise)
    assert abs(fits[0].camera.K[0, 0] / truth.K[0, 0] - 1) < 0.005
    # before the fix, 6 calls gave 6 different results on OpenCV's threads (measured on the sample's boards)
    assert len({_bits(f) for f in fits}) == 1
    # the caller's OpenCV thread count is left as it was
    assert cv2.getNumThreads() == threads
