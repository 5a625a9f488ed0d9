"""organlab: from a specimen on a turntable to a measured, watertight 3D model.

The whole pipeline, one public function per stage::

    import organlab as ol
    s = ol.load_session("sample_sessions/aaa_phantom")
    cal = ol.calibrate(s)                        # or ol.Calibration.load(path); cal.save(path)
    sils = ol.silhouettes(s, threshold=None)
    grid = ol.VoxelGrid.from_session(s, voxel_size=1.0)
    field = ol.hull_field(sils, cal.cameras(s), grid, sparse=True)
    mesh = ol.mesh_from_field(field, grid)
    mesh = ol.finish_surface(mesh, voxel_size=1.0).mesh     # repaired, remeshed
    ol.measure(mesh)                             # MeshMeasures: volume, area, watertight

Stages, one module (or package) each: :mod:`organlab.session` (session
folders), :mod:`organlab.camera` (the camera model),
:mod:`organlab.calibration`, :mod:`organlab.silhouette`,
:mod:`organlab.carving`, :mod:`organlab.coloring`, :mod:`organlab.surface`,
and :mod:`organlab.pipeline`, which chains them (:func:`reconstruct`).
Names other than the light ones below load their module on first use, so
``import organlab`` stays fast.
"""

import os
from importlib import import_module

# numba tries its TBB threading layer first; pymeshlab ships a libtbb older than numba accepts, and once
# pymeshlab is loaded that choice warns (an error under the tests' filterwarnings) before falling back.
# OpenMP first: thread-safe like TBB (the viewer's worker thread).  Read by numba when it is first imported.
os.environ.setdefault("NUMBA_THREADING_LAYER_PRIORITY", "omp workqueue tbb")

from .camera import Camera
from .errors import CalibrationError, OrganlabError, SessionError
from .grid import VoxelGrid
from .session import Session, load_session

__version__ = "0.2.0"

#: Public name -> module that defines it (loaded on first access).
_LAZY = {
    "Calibration": "calibration",
    "calibrate": "calibration",
    "calibration_for": "calibration",
    "Silhouette": "silhouette",
    "silhouettes": "silhouette",
    "hull_field": "carving",
    "carve": "carving",
    "ProgressiveCarver": "carving",
    "color_voxels": "coloring",
    "Mesh": "surface",
    "mesh_from_field": "surface",
    "mesh_from_volume": "surface",
    "measure": "surface",
    "finish_surface": "surface",
    "FinishedSurface": "surface",
    "Reconstruction": "pipeline",
    "reconstruct": "pipeline",
    "write_outputs": "pipeline",
    "sweep": "batch",
}

__all__ = ["Camera", "VoxelGrid", "Session", "load_session", "OrganlabError", "SessionError", "CalibrationError",
           *_LAZY]


def __getattr__(name):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'organlab' has no attribute {name!r}")
    value = getattr(import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
