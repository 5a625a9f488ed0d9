"""The silhouette of a view: the plain type every stage passes (ground floor).

:func:`organlab.silhouette.silhouettes` makes them; the carving, colouring
and agreement stages read their ``mask`` (bool) or ``coverage`` (sub-pixel).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Sequence

import numpy as np

__all__ = ["Silhouette", "as_arrays"]


@dataclass(frozen=True)
class Silhouette:
    """The silhouette of one view.

    Attributes
    ----------
    mask : (H, W) bool
    coverage : (H, W) float32 in [0, 1]
        Sub-pixel silhouette (equal to ``mask`` for a given mask).
    threshold : float or None
        Grey-level threshold used (None for a given mask).
    source : str
        ``'subtraction'``, ``'backdrop'`` (keyed, see :mod:`organlab.silhouette`) or ``'given'``.
    info : dict or None
        How a keyed view was thresholded (threshold's reason, noise, clutter,
        Li's threshold, exposure gain, shadow fraction, closing radius).
    """

    mask: np.ndarray
    coverage: np.ndarray
    threshold: float | None
    source: str
    info: dict | None = None


def as_arrays(silhouettes: Sequence, attribute: Literal["mask", "coverage"]) -> list[np.ndarray]:
    """The masks or coverages of a list of silhouettes, for the carving functions.

    Parameters
    ----------
    silhouettes : sequence of Silhouette or of (H, W) arrays
        What :func:`silhouettes` returns, or plain arrays (passed through).
    attribute : {'mask', 'coverage'}

    Returns
    -------
    list of (H, W) arrays
    """
    return [getattr(s, attribute) if isinstance(s, Silhouette) else s for s in silhouettes]
