"""A live 3D viewer in the browser (viser): watch the hull grow, tune it by hand.

* :class:`LiveView` -- a scene that carving and capture stream partial results
  to (``add_view(image, camera, silhouette)``, ``set_voxels``, ``set_mesh``);
* :class:`SessionViewer` -- a session with its reconstruction and the controls
  that re-run it (``organlab view SESSION``);
* :class:`CaptureViewer` -- a LiveView following a capture
  (``organlab capture ... --view``);
* :func:`is_loopback` -- whether a ``host`` is this machine only (any other needs
  the viewer's token in the URL: :mod:`organlab.viewer._access`).

viser (a heavy optional library) is imported only when one of them is
constructed: importing this package does not load it.
"""

from ._access import is_loopback
from ._app import SessionViewer, Settings
from ._capture import CaptureViewer
from ._live import LiveView

__all__ = ["CaptureViewer", "LiveView", "SessionViewer", "Settings", "is_loopback"]
