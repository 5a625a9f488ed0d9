"""Camera and turntable calibration from images of a checkerboard.

Two fits, each reported with the errors a user needs to judge it before
carving (:func:`check_figures` draws them over every image):

* **Intrinsics** (:func:`calibrate_intrinsics`): the board held at varied
  poses.  Bouguet's camera model (``fc``, ``cc``, ``alpha_c``,
  ``kc = [k1, k2, p1, p2, k3]``) fitted with OpenCV's
  ``calibrateCameraExtended`` (or, with ``estimate_skew=True``, a joint
  least-squares fit that also frees ``alpha_c``), per-image reprojection RMS,
  automatic rejection of images whose RMS is far above the others and a
  second pass without them, and the standard deviation of every parameter.
  Like Bouguet's toolbox, :attr:`IntrinsicCalibration.uncertainty` gives
  **three** standard deviations.
* **Turntable** (:func:`calibrate_turntable`): the board lying on the table,
  one image per known table angle.  One least-squares problem over every
  corner of every image (8 unknowns: the camera pose at angle 0 (6) and the
  board's in-plane position relative to the table axis (2)), the angles held
  at their given values, initialised from per-image ``solvePnP``.  Images
  whose residual is far above the others (the board moved) are flagged and
  left out of a second pass.

World frame (``session-format.md``): defined by the board at table angle 0:
X along the board's long side (``inner_corners[0]``) from the end whose
corner squares are black toward the end whose corner squares are white,
Z the table axis toward the camera's side (up), Y = Z x X, origin where the
axis meets the board's top surface.  :func:`detect_board` returns corners in
that board order whatever order the corner detector found them in.

The result of a session's calibration is one :class:`Calibration` (intrinsics, turntable,
pattern, a fingerprint of what it was computed from) with ``save``/``load`` (``calibration.json``)
and ``cameras(session)``.  :func:`calibrate` computes it; :func:`calibration_for` picks the one a
reconstruction should use.  The check figures are drawn by :func:`organlab.figures.check_figures`.

Calibrations made by other tools (Bouguet's ``Calib_Results.m``, OpenCV's YAML/XML) are read and
written by :func:`read_bouguet`, :func:`write_bouguet`, :func:`read_opencv`, :func:`write_opencv`
and :func:`read_camera` (either format, by its suffix).

Private modules: ``_board`` (board geometry and corner detection), ``_intrinsics``,
``_turntable``, ``_result`` (the :class:`Calibration` type, its file form, session glue),
``_files`` (other tools' calibration files), ``_common`` (thresholds, geometry, input checks),
``_formats`` (posed cameras of other tools in and out: :func:`read_cameras`, :func:`write_cameras`).
"""

from ._board import board_points, detect_board
from ._files import read_bouguet, read_camera, read_opencv, write_bouguet, write_opencv
from ._formats import CAMERA_FORMATS, CameraFile, camera_format, export_cameras, read_cameras, write_cameras
from ._intrinsics import IntrinsicCalibration, calibrate_intrinsics, fit_intrinsics
from ._result import Calibration, calibrate, calibration_for, needs_calibration, session_fingerprint
from ._turntable import TurntableCalibration, calibrate_turntable, fit_turntable

__all__ = [
    "Calibration",
    "calibrate",
    "calibration_for",
    "needs_calibration",
    "session_fingerprint",
    "board_points",
    "detect_board",
    "IntrinsicCalibration",
    "TurntableCalibration",
    "calibrate_intrinsics",
    "fit_intrinsics",
    "calibrate_turntable",
    "fit_turntable",
    "read_bouguet",
    "write_bouguet",
    "read_opencv",
    "write_opencv",
    "read_camera",
    "CAMERA_FORMATS",
    "CameraFile",
    "camera_format",
    "export_cameras",
    "read_cameras",
    "write_cameras",
]
