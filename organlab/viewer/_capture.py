"""CaptureViewer: the live viewer following a capture (``organlab capture --view``).

The capture calls :meth:`CaptureViewer.on_view` after each view it saves
(``organlab.capture``'s ``on_view(index, angle_deg, image)`` hook).  The views
come after the background frames and the board images on the table, so at the
first view everything the viewer needs is in the session folder: the
calibration (the camera at table angle 0), the background frames (or the
backdrop) and the roi, which :meth:`organlab.engine.LiveHull.for_capture`
reads.  From then on each image is shown at its camera, and the engine's live
hull finds its silhouette (as ``organlab reconstruct`` does: background
subtraction, or keying against the session's backdrop) and carves with it.  A failure of the display is reported
once and switches the viewer off; it never stops the capture.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..engine import LiveHull
from ..session import load_session
from ._live import LiveView


class CaptureViewer:
    """A :class:`LiveView` fed by a capture of the session folder ``session_dir``.

    Parameters
    ----------
    session_dir : str or Path
        The folder the capture writes (``session.json``).
    voxel_size : float, mm
        Voxel edge of the progressive hull (2 mm keeps each view's carving
        short on a capture machine).
    threshold : float, optional
        Silhouette threshold, grey levels (automatic per view when omitted,
        at least 5 x the background noise, as ``organlab reconstruct`` does);
        Delta E for a session keyed against a backdrop.
    tolerance : int
        Views allowed to disagree before a voxel is carved.
    host, port, verbose, token : as :class:`LiveView`
    say : callable(str), optional
        Where the note is printed when the viewer switches off (default: stderr).

    Attributes
    ----------
    live : LiveView
    camera0 : Camera or None
        The calibrated camera at table angle 0 (after the first view).
    hull : organlab.engine.LiveHull or None
        The hull carved so far (after the first view).
    error : str or None
        Why the viewer stopped following the capture.
    """

    def __init__(self, session_dir: str | Path, *, voxel_size: float = 2.0, threshold: float | None = None,
                 tolerance: int = 0, host: str = "127.0.0.1", port: int = 8080, verbose: bool = False,
                 say: Callable[[str], None] | None = None, token: str | None = None):
        if not voxel_size > 0:
            raise ValueError(f"voxel_size must be > 0 mm, got {voxel_size}")
        self.root = Path(session_dir)
        self.voxel_size = float(voxel_size)
        self.threshold = threshold
        self.tolerance = int(tolerance)
        self.say = say if say is not None else (lambda s: print(s, file=sys.stderr))
        self.live = LiveView(host=host, port=port, verbose=verbose, label=f"organlab capture: {self.root.name}",
                             token=token)
        self.camera0 = None
        self.hull = None
        self.error = None
        self._listener = None

    @property
    def url(self) -> str:
        return self.live.url

    def on_view(self, index: int, angle_deg: float, image: np.ndarray) -> None:
        """The capture's ``on_view`` hook: show view ``index`` (taken at ``angle_deg``) and carve with it.

        Parameters
        ----------
        index : int
            The view's index in ``session.json`` (the views of an earlier run
            of the same capture are shown from disk first).
        angle_deg : float
            Table angle, deg.
        image : (H, W, 3) uint8
        """
        if self.error is not None:
            return
        try:
            if self._listener is None:
                self._start(index)
            self._listener(index, angle_deg, image)
        except Exception as e:  # noqa: BLE001 -- the display must never stop the capture; said once, with its cause
            self.error = f"{type(e).__name__}: {e}" if not str(e) else str(e)
            self.say(f"organlab capture: live view off: {self.error}")

    def _start(self, index):
        """The engine's live hull from the session so far; earlier views from disk."""
        s = load_session(self.root)
        self.hull = LiveHull.for_capture(s, voxel_size=self.voxel_size, threshold=self.threshold,
                                         tolerance=self.tolerance)
        self.camera0 = self.hull.camera0
        self.live.frame(*self.hull.grid.bounds)

        def listener(k, angle_deg, image):
            camera = self.camera0.at_table_angle(angle_deg)
            sil, occ = self.hull.add_image(image, camera)
            self.live.add_view(image, camera, sil)
            if occ is not None:
                self.live.set_voxels(occ, self.hull.grid)

        for k, v in enumerate(s.views[:index]):  # taken by an earlier run of this capture
            listener(k, v.angle_deg, s.read(v.image, key=f"views[{k}].image"))
        self._listener = listener

    def stop(self) -> None:
        """Stop the server (frees the port)."""
        self.live.stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
