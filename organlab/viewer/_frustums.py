"""The cameras before and after pose refinement (issue 20), and each view's correction.

:class:`PoseFrustums` draws, in a :class:`~organlab.viewer.LiveView`'s scene,
the frustum of every view whose pose the ``poses`` stage changed twice: where
the board calibration put it (red, ``/poses/before/NNN``) and where the
refinement put it (green, ``/poses/after/NNN``), joined by a line from the old
centre to the new one; and a panel (``Poses``) with the stage's decision, the
change of the shared camera pose, a slip, and the per-view angle corrections
of ``report.json``'s ``poses`` entry.  The views' own grey frustums (with
their photos) stay where the viewer put them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..camera import Camera
from . import _scene

BEFORE_COLOR = (210, 50, 50)
AFTER_COLOR = (40, 170, 80)


def changed_views(before: Sequence[Camera], after: Sequence[Camera], *, tol_mm: float = 1e-6) -> list[int]:
    """Indices of the views whose pose differs between ``before`` and ``after``.

    Parameters
    ----------
    before, after : sequences of Camera, the same length
    tol_mm : float
        Largest centre move (mm) and rotation (rad) taken as no change.

    Returns
    -------
    list of int

    Examples
    --------
    >>> import numpy as np
    >>> from organlab.camera import Camera
    >>> a = Camera(np.eye(3), np.zeros(5), np.eye(3), np.zeros(3), image_size=(4, 4))
    >>> changed_views([a, a], [a, a.with_pose(np.eye(3), np.array([0.0, 0.0, 1.0]))])
    [1]
    """
    if len(before) != len(after):
        raise ValueError(f"before and after must be as long, got {len(before)} and {len(after)} cameras")
    out = []
    for i, (b, a) in enumerate(zip(before, after)):
        if np.linalg.norm(a.center - b.center) > tol_mm or np.abs(a.R - b.R).max() > tol_mm:
            out.append(i)
    return out


def corrections_markdown(poses: dict | None, names: Sequence[str] | None = None, *, limit: int = 12) -> str:
    """The ``poses`` entry of ``report.json`` as the viewer's panel text (markdown).

    Parameters
    ----------
    poses : dict or None
        :meth:`organlab.poses.PoseRefinement.to_dict`.
    names : sequence of str, optional
        View labels (default the report's).
    limit : int
        The largest corrections listed.

    Returns
    -------
    str

    Examples
    --------
    >>> corrections_markdown(None)
    '**Poses** not refined'
    """
    if not poses:
        return "**Poses** not refined"
    lines = [f"**Poses** {poses.get('reason', '')}"]
    if poses.get("angle_prior"):
        lines.append(f"angles held to {poses['angle_prior']}")
    if poses.get("accepted") or poses.get("audit_applied"):
        shift = poses.get("camera_center_shift_mm")
        if poses.get("camera_rotation_deg") is not None and shift is not None:
            lines.append(f"camera turned {poses['camera_rotation_deg']:.3f} deg, moved "
                         f"{float(np.linalg.norm(np.asarray(shift, float))):.2f} mm")
        s = poses.get("slip")
        if s:
            lines.append(f"specimen slid from view {s['view']}: ({s['translation_mm'][0]:+.2f}, "
                         f"{s['translation_mm'][1]:+.2f}) mm, {s['rotation_deg']:+.2f} deg")
        views = poses.get("views") or []
        ranked = sorted(range(len(views)), key=lambda i: -abs(views[i].get("angle_correction_deg") or 0.0))[:limit]
        cells = []
        for i in sorted(ranked):
            v = views[i]
            c = v.get("angle_correction_deg")
            if c is None or abs(c) < 5e-4:
                continue
            label = names[i] if names is not None and i < len(names) else v.get("view", i)
            cells.append(f"`{label}: {c:+.2f}°`")
        if cells:
            lines.append("angle corrections: " + " ".join(cells))
    tr = poses.get("tangent_rms_px")
    if tr:
        lines.append(f"tangent RMS {tr['before_median']:.2f} -> {tr['after_median']:.2f} px (median over the views)")
    return "  \n".join(lines)


class PoseFrustums:
    """Frustums before (red) and after (green) pose refinement, and the corrections panel.

    Parameters
    ----------
    live : organlab.viewer.LiveView
        Its scene and GUI get the frustums and the panel.

    Examples
    --------
    >>> from organlab.viewer._frustums import PoseFrustums  # doctest: +SKIP
    >>> PoseFrustums(live).show(before_cameras, after_cameras, report["poses"])  # doctest: +SKIP
    """

    def __init__(self, live) -> None:
        self.live = live
        self._handles = []
        self._panel = None
        self.shown: list[int] = []

    def clear(self) -> None:
        """Remove the frustums (the panel stays, emptied)."""
        for h in self._handles:
            h.remove()
        self._handles = []
        self.shown = []

    def show(self, before: Sequence[Camera], after: Sequence[Camera], poses: dict | None,
             names: Sequence[str] | None = None) -> list[int]:
        """Draw the views whose pose changed, twice; write the panel.

        Returns
        -------
        list of int
            The views drawn (whose pose changed).
        """
        self.clear()
        server = self.live.server
        if self._panel is None:
            with server.gui.add_folder("Poses"):
                self._panel = server.gui.add_markdown("")
        self._panel.content = corrections_markdown(poses, names)
        if len(before) != len(after):
            return []
        moved = changed_views(before, after)
        roi = np.asarray(self.live._roi, dtype=np.float64)
        middle = roi.mean(axis=0)
        segments = []
        for i in moved:
            for kind, cam, color in (("before", before[i], BEFORE_COLOR), ("after", after[i], AFTER_COLOR)):
                wxyz, pos, fov, aspect = _scene.camera_pose(cam)
                dist = float(np.linalg.norm(pos - middle))
                self._handles.append(server.scene.add_camera_frustum(
                    f"/poses/{kind}/{i:03d}", fov=fov, aspect=aspect, scale=_scene.frustum_scale(fov, aspect, 0.07 * dist),
                    thickness=0.0015 * dist, color=color, wxyz=wxyz, position=pos))
            segments.append([before[i].center, after[i].center])
        if segments:
            pts = np.asarray(segments, dtype=np.float32)
            self._handles.append(server.scene.add_line_segments(
                "/poses/moves", pts, np.tile(np.array(AFTER_COLOR, np.uint8), (len(pts), 2, 1)),
                thickness=0.003 * float(np.linalg.norm(pts[0, 0] - middle))))
        self.shown = moved
        return moved
