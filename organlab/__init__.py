"""organlab: from a specimen on a turntable to a measured, watertight 3D model.

Stages, one module each: :mod:`organlab.session` (session folders),
:mod:`organlab.camera` (the camera model), :mod:`organlab.calibration`,
:mod:`organlab.silhouette`, :mod:`organlab.carving`, :mod:`organlab.coloring`,
:mod:`organlab.surface`, and :mod:`organlab.pipeline` which chains them.
Heavy modules load only when used, so ``import organlab`` stays fast.
"""

from .camera import Camera
from .errors import CalibrationError, OrganlabError, SessionError
from .grid import VoxelGrid
from .session import load_session

__version__ = "0.1.0"

__all__ = ["Camera", "VoxelGrid", "load_session", "OrganlabError", "SessionError", "CalibrationError"]
