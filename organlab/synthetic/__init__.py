"""Synthetic sessions: a known camera, a known specimen, rendered images.

Every image is ray cast through the full :class:`~organlab.camera.Camera`
model (``Camera.rays`` of supersampled sub-pixel positions, box filter), so
the lens distortion in the images is exactly the one ``Camera.project``
models, and sub-pixel methods (corner detection, silhouettes) can be tested
against the truth.

Scene (world frame = turntable frame, mm, Z up along the table axis):

* a turntable plate, a grey disk of radius 125 mm whose top is ``z = 0``,
  rotationally symmetric so it looks the same at every table angle;
* a dark backdrop fixed to the camera (a function of the ray direction in the
  camera frame), so background frames match the views;
* lighting fixed to the camera, mostly ambient with mild diffuse shading
  (``hard=True``: a lamp with cast shadows, highlights, exposure changes of
  +-10 % and JPEG views, see ``_hard``);
* a checkerboard printed on a zero-thickness sheet, and a specimen
  (:class:`AAAPhantom`, :class:`GroovedSpecimen`, :class:`DentedSpecimen`,
  :class:`Sphere`, :class:`Cylinder`) standing on the plate.

What went wrong at the rig can be simulated (``make_session``): the true table
angles (a table that lost steps, a mislabelled view: ``true_angles_deg``), a camera
bumped after the board images (``camera_bump``), a specimen that slid on the plate
from a view on (``slip``, :class:`Moved`); ``truth.json`` then holds the true poses.
``AAAPhantom(shape_seed=N)`` (``make_specimen("aaa-N")``) is another AAA of the
sample's family; :class:`BranchedAAA` (``make_specimen("aaa-N+branch")``) the same with two
renal-artery-like stumps near its top, whose outline shows the table's angles.

``python -m organlab.synthetic OUT --seed 0`` writes a complete session
folder in the ``organlab.session/1`` format, with ``truth.json`` beside it.

Private modules: ``_boards`` (camera, board poses and images), ``_specimens``,
``_render`` (ray casting, shading), ``_hard`` (the hard lamp), ``_views``
(views and silhouettes), ``_session`` (the session folder), ``_truth``
(distance to a specimen's exact surface, to score a mesh), ``_simrig``
(the simulated capture rig: MDrive controller on a pty, rendering camera), ``_cli``.
"""

__all__ = [
    "DEFAULT_PATTERN",
    "default_camera",
    "board_object_points",
    "board_outline",
    "turntable_board_pose",
    "turntable_board_points",
    "intrinsic_board_poses",
    "render_board",
    "tissue_albedo",
    "Specimen",
    "Sphere",
    "Cylinder",
    "AAAPhantom",
    "BranchedAAA",
    "GroovedSpecimen",
    "DentedSpecimen",
    "Moved",
    "striped_albedo",
    "make_specimen",
    "render_view",
    "render_masks",
    "make_session",
    "with_true_cameras",
    "DEFAULT_ROI",
    "BOARD_CENTER_XY",
    "BOARD_MARGIN",
    "main",
    "distance_to_specimen",
    "surface_samples",
    "SimRig",
    "SimCamera",
    "MDriveSimulator",
    "make_lit_session",
    "render_lit",
    "Painted",
]

from ._boards import (
    BOARD_CENTER_XY,
    BOARD_MARGIN,
    DEFAULT_PATTERN,
    board_object_points,
    board_outline,
    default_camera,
    intrinsic_board_poses,
    render_board,
    turntable_board_points,
    turntable_board_pose,
)
from ._cli import main
from ._lighting import Painted, make_lit_session, render_lit
from ._session import DEFAULT_ROI, make_session, with_true_cameras
from ._specimens import (
    AAAPhantom,
    BranchedAAA,
    Cylinder,
    DentedSpecimen,
    GroovedSpecimen,
    Moved,
    Specimen,
    Sphere,
    make_specimen,
    striped_albedo,
    tissue_albedo,
)
from ._simrig import MDriveSimulator, SimCamera, SimRig
from ._truth import distance_to_specimen, surface_samples
from ._views import render_masks, render_view
