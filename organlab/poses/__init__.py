"""Pose refinement from the silhouettes: the views' poses corrected so that the silhouettes agree.

After the board-based calibration and the silhouettes, before carving.  The
camera's pose relative to the table axis (shared by every view) and each
view's table angle (with a prior that the angles follow the commanded ones and
drift smoothly) are fitted so that every pair of silhouettes has the same
outer epipolar tangent planes (frontier points under circular motion:
Mendonca, Wong & Cipolla 2001); a specimen that slid on the plate from some
view on is found as a step in the pairs' residuals and fitted as a rigid move
on the plate.  The result is used only when views left out of the fit agree
better with the others afterwards (leave-out folds): a rotation-symmetric
specimen, which hides its angles, is left alone and the report says so.
When the capture's angle audit measured the stops (``session.json``
``capture.audit``, :func:`organlab.capture.audited_angles`), the views'
angles are held to the measured ones instead of the commanded ones.
When the shared camera moved and ``session.json`` gives the turntable plate's
diameter (``turntable_plate``), the camera's distance to the table axis and its
height, which no silhouette shows, are measured on the plate's rim in the empty
scene and fitted with the tangents.

``refine_poses(session, calibration, silhouettes, mode=...)`` is the stage's
one function; it returns a :class:`PoseRefinement` (``.cameras`` to carve
with, ``.to_dict()`` for ``report.json``).

Private modules: ``_outline`` (the edge pixels' coverage re-estimated from the
images, for sub-pixel outlines), ``_tangents`` (outline rays, extremal epipolar planes),
``_model`` (the pose model, its residuals and the robust fit), ``_plate`` (the
plate's rim: the camera's distance to the axis and height), ``_refine``
(detection, slip, gate).  Silhouette coherence along outline rays was tried and
dropped (docs/trust.md says why).
"""

from ._outline import warm_kernels
from ._refine import FLAG_PX, FLAG_SUBPIXEL_PX, MODES, PoseRefinement, refine_poses

__all__ = ["refine_poses", "PoseRefinement", "MODES", "FLAG_PX", "FLAG_SUBPIXEL_PX", "warm_kernels"]
