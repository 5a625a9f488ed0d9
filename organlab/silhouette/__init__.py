"""Silhouettes: background model, subtraction, threshold, clean-up, backdrop keying.

The specimen's silhouette in a view is where the view differs from the empty
scene.  The stage is a chain of small functions::

    bg = background_model(frames)                 # mean or median of empty frames
    diff = difference(image, bg)                  # grey or colour distance
    t = auto_threshold(diff)                      # Li's, or a value picked by the user
    mask = clean_mask(diff > t)                   # opening, closing, components, holes
    mask = grow_rim(mask, diff, image, bg, noise=n)  # its dim rim (hysteresis down to 3 noise sigmas)
    cov = coverage(image, bg, mask)               # sub-pixel silhouette in [0, 1]

:func:`silhouettes` runs it for every view of a session (through
:class:`SilhouetteModel`, which keeps what does not depend on the
threshold), using a view's own ``mask`` where the session gives one, and
keying in CIE Lab against a ``backdrop`` when the session declares one.
:meth:`SilhouetteModel.joint` then segments every view again with the
hull of all the views as a prior (the joint step, ``_joint``;
``docs/silhouettes.md``).  The result type, :class:`~organlab.masks.Silhouette`, lives on the ground
floor (:mod:`organlab.masks`) so every stage can read it.

Modules: ``_subtract`` (the functions above), ``_keying`` (backdrop keying),
``_model`` (:class:`SilhouetteModel`, :func:`silhouettes`), ``_joint`` (the joint step), ``_kernels``
(numba kernels).
"""

from ..masks import Silhouette, as_arrays
from ._kernels import warm_kernels
from ._model import SilhouetteModel, session_silhouettes, silhouettes
from ._subtract import (
    auto_threshold,
    background_model,
    background_noise,
    clean_mask,
    coverage,
    difference,
    grow_rim,
    silhouette,
)

__all__ = [
    "background_model",
    "background_noise",
    "difference",
    "auto_threshold",
    "clean_mask",
    "grow_rim",
    "coverage",
    "Silhouette",
    "silhouette",
    "silhouettes",
    "session_silhouettes",
    "as_arrays",
    "SilhouetteModel",
    "warm_kernels",
]
