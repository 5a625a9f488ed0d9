"""Checks for a model that is too big (issue 26): what view agreement cannot see.

:mod:`organlab.agreement` counts the silhouette pixels a model fails to cover, so it flags a
model that is too *small*.  A visual hull is too *big* wherever no view looked: with one view it
is the silhouette swept to the roi's walls (measured on the sample AAA: +393 % volume, a 170 mm
"diameter"), with two +29 %, with ``tolerance >= views`` the whole roi box (+2266 %), and every
one of these runs agrees with its views perfectly.  These checks look at the run itself:

- :func:`check_tolerance`: a negative tolerance is an error; one at or above the number of
  views keeps every voxel (a warning).
- :func:`model_warnings`: one or two views; views spanning less than :data:`MIN_SPAN_DEG` of
  the table; a model touching the roi's faces (cut off there, or swept to them), with the faces
  and an roi that would contain it.

Each warning says what the volume then means.  ``organlab reconstruct --strict`` refuses a run
with a warning (exit status 2).
"""

from __future__ import annotations

import numpy as np

from .errors import SessionError

__all__ = ["MIN_SPAN_DEG", "check_tolerance", "model_warnings", "roi_faces_touched", "view_span_deg"]

#: Views must look from at least this much of the table.  A silhouette seen from angle a bounds the
#: model as the one from a + 180 (mirrored) does, so half a turn sights every direction once; below
#: it, directions no view sighted along are bounded only by the other views' sweep.  Measured on the
#: synthetic AAA (seed 7, 4 mm, no finishing): 12 views over 330 degrees -0.5 % volume, 6 views over
#: 150 degrees +2.8 %, 2 views at 0 and 90 +29.0 %, 1 view +393 %.
MIN_SPAN_DEG = 180.0

_FACES = ("x min", "x max", "y min", "y max", "z min", "z max")


def check_tolerance(tolerance, n_views, *, where="--tolerance"):
    """Refuse a negative or non-integer tolerance; a warning (str) when it keeps every voxel, else None.

    Examples
    --------
    >>> check_tolerance(0, 12) is None
    True
    """
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, np.integer)) or tolerance < 0:
        raise SessionError(f"{where} must be a whole number of views >= 0 (views allowed to disagree), got {tolerance!r}")
    if n_views and tolerance >= n_views:
        return (f"tolerance {int(tolerance)} >= the {n_views} views: no view can carve a voxel, the model is the whole "
                "roi box and its volume the roi's, not the specimen's; use a tolerance below the number of views (0-2)")
    return None


def view_span_deg(cameras):
    """Degrees of the table (about the world +Z axis) the camera centres span: 360 less the largest gap.

    Examples
    --------
    >>> from organlab.camera import Camera
    >>> K = [[100, 0, 50], [0, 100, 50], [0, 0, 1]]
    >>> centres = [[500, 0, 300], [0, 500, 300]]  # at 0 and 90 degrees about the axis
    >>> cams = [Camera(K, None, np.eye(3), -np.asarray(c, float)) for c in centres]
    >>> round(view_span_deg(cams))
    90
    """
    az = np.sort([np.degrees(np.arctan2(c.center[1], c.center[0])) % 360.0 for c in cameras])
    if az.size < 2:
        return 0.0
    gaps = np.diff(np.append(az, az[0] + 360.0))
    return float(360.0 - gaps.max())


def roi_faces_touched(occupancy, roi_min, voxel_size):
    """The roi faces (``"x min"`` ... ``"z max"``) the model reaches; the floor at the table top (z = 0) is expected.

    Examples
    --------
    >>> import numpy as np
    >>> from organlab.checks import roi_faces_touched
    >>> occ = np.zeros((4, 4, 4), bool); occ[1:, 1:3, 0:2] = True
    >>> roi_faces_touched(occ, [0.0, 0.0, 0.0], 1.0), roi_faces_touched(occ, [0.0, 0.0, 10.0], 1.0)
    (['x max'], ['x max', 'z min'])
    """
    return _touched_faces(occupancy, np.asarray(roi_min, float), voxel_size)


def _touched_faces(occupancy, roi_min, voxel_size):
    occ = np.asarray(occupancy, dtype=bool)
    touched = [occ[0].any(), occ[-1].any(), occ[:, 0].any(), occ[:, -1].any(), occ[:, :, 0].any(), occ[:, :, -1].any()]
    # the specimen stands on the table (z = 0): a model on an roi floor at the table top is expected
    if abs(float(roi_min[2])) <= voxel_size:
        touched[4] = False
    return [f for f, t in zip(_FACES, touched) if t]


def model_warnings(cameras, occupancy, roi_min, roi_max, *, voxel_size, tolerance=0, disagreeing=()):
    """Warnings for a model that is too big, each with what its volume then means.

    Parameters
    ----------
    cameras : list of Camera
        The views' cameras, world frame (mm).
    occupancy : (nx, ny, nz) bool
        The carved model on the grid spanning ``roi_min``..``roi_max``.
    roi_min, roi_max : (3,) float, mm
    voxel_size : float, mm
    tolerance : int
        Views allowed to disagree (:func:`check_tolerance`).
    disagreeing : sequence of str
        The views the agreement check flagged (e.g. ``"views/180.jpg 68 px"``).  A model cut by
        the roi leaves silhouette unexplained where it is cut: the roi's warning names them, so that
        the cut is one warning, not one about the roi and one blaming the poses.

    Returns
    -------
    list of str

    Examples
    --------
    >>> from organlab.camera import Camera
    >>> cam = Camera([[100, 0, 50], [0, 100, 50], [0, 0, 1]], None, np.eye(3), [0, 0, 500])
    >>> len(model_warnings([cam], np.zeros((4, 4, 4), bool), [0, 0, 0], [4, 4, 4], voxel_size=1.0))
    1
    """
    out = []
    n = len(cameras)
    t = check_tolerance(tolerance, n)
    if t:
        out.append(t)
    if 0 < n <= 2:
        out.append(f"only {n} view{'s' if n > 1 else ''}: the model is the silhouette{'s' if n > 1 else ''} swept "
                   "along the viewing direction to the roi, so its volume is an upper bound, not a measure "
                   "(+393 % with one view, +29 % with two at 90 degrees on a synthetic AAA); use 12 or more views around the table")
    span = view_span_deg(cameras)
    if n > 2 and span < MIN_SPAN_DEG:
        out.append(f"the views span only {span:.0f} degrees of the table (less than {MIN_SPAN_DEG:.0f}): directions "
                   "no view sighted along are bounded only by the other views' sweep, so the volume is an upper bound "
                   "(+2.8 % with 6 views over 150 degrees on a synthetic AAA); take views around at least half the table")
    roi_min, roi_max = np.asarray(roi_min, float), np.asarray(roi_max, float)
    faces = _touched_faces(occupancy, roi_min, voxel_size)
    if faces:
        ext = roi_max - roi_min
        lo, hi = roi_min.copy(), roi_max.copy()
        for f in faces:  # half the roi's size again beyond every touched face
            axis, side = "xyz".index(f[0]), f[2:]
            if side == "min":
                lo[axis] -= ext[axis] / 2
            else:
                hi[axis] += ext[axis] / 2
        views = list(disagreeing)
        flagged = (f"; the {len(views)} view{'s that disagree' if len(views) > 1 else ' that disagrees'} with the model "
                   f"({', '.join(views[:5])}{' and more' if len(views) > 5 else ''}) likely do so because of the cut"
                   if views else "")
        out.append(f"the model touches the roi's {', '.join(faces)} face{'s' if len(faces) > 1 else ''}: it is cut "
                   "off there (or swept to them by too few views), so its volume and sizes are not the specimen's; "
                   f"enlarge the roi, e.g. min {_mm(lo)}, max {_mm(hi)}{flagged}")
    return out


def _mm(v):
    return "[" + ", ".join(f"{x:g}" for x in np.round(v, 1)) + "]"
