"""Interactive helpers for notebooks: pick a threshold, check a calibration, tune the carving.

Each helper is a plain Python class that holds its parameters and calls the
stage functions (:mod:`organlab.silhouette`, :mod:`organlab.calibration`,
:mod:`organlab.carving`, :mod:`organlab.coloring`, :mod:`organlab.surface`);
its ``figure()`` draws the current state with matplotlib and its
``widget()`` wraps it in ipywidgets controls.  The classes work without a
browser or a kernel (set attributes, read results); ipywidgets is imported
only by ``widget()``.

* :class:`ThresholdPicker` -- silhouette threshold of any view: mask over the
  image, difference histogram with the chosen and the automatic threshold,
  silhouette area.
* :class:`CalibrationChecker` -- intrinsic calibration images: detected and
  reprojected corners with magnified residuals, per-image errors, drop an
  image and recalibrate, uncertainties before and after.
* :class:`CarvingTuner` -- voxel size, tolerance, colour threshold: volume,
  per-view agreement of the model with the silhouettes, a picture of the mesh.
"""

from ._calibration import CalibrationChecker
from ._carving import CarvingTuner
from ._threshold import ThresholdPicker

__all__ = ["ThresholdPicker", "CalibrationChecker", "CarvingTuner"]
