"""A live 3D viewer in the browser (viser): watch the hull grow, tune it by hand.

* :class:`LiveView` -- a scene that carving and capture stream partial results
  to (``add_view(image, camera, silhouette)``, ``set_voxels``, ``set_mesh``);
* :class:`SessionViewer` -- a session with its reconstruction and the controls
  that re-run it (``organlab view SESSION``);
* :class:`CaptureViewer` -- a LiveView following a capture
  (``organlab capture ... --view``).

* :func:`is_loopback` -- whether a ``host`` is this machine only (any other needs
  the viewer's token in the URL: :mod:`organlab.viewer._access`).

viser is imported only when one of them is used.
"""

from ._access import is_loopback

__all__ = ["CaptureViewer", "LiveView", "SessionViewer", "Settings", "is_loopback"]


def __getattr__(name):
    if name == "LiveView":
        from ._live import LiveView

        return LiveView
    if name == "CaptureViewer":
        from ._capture import CaptureViewer

        return CaptureViewer
    if name in ("SessionViewer", "Settings"):
        from . import _app

        return getattr(_app, name)
    raise AttributeError(f"module 'organlab.viewer' has no attribute {name!r}")
