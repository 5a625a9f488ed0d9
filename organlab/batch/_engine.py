"""The engine this package runs (organlab.engine, issue 19), or a stand-in until it is merged.

The stand-in has the contract's ``Settings`` and an ``Engine`` whose ``run`` is
:func:`organlab.pipeline.reconstruct` (no stage cache): it is replaced by the
real engine at merge time and is not public.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

try:  # the real engine (issue 19)
    from ..engine import Engine, Settings  # noqa: F401
except ImportError:  # until the engine branch is merged
    from ..pipeline import HULL_METHODS, METHODS, reconstruct

    @dataclass(frozen=True)
    class Settings:
        voxel_size: float = 1.0
        threshold: float | None = None
        method: str = "hull"
        hull: str = "subvoxel"
        color_threshold: float | None = None
        tolerance: int = 0
        finish: bool = True
        measure: bool | None = None
        roi: tuple | None = None

        def replace(self, **changes):
            return dataclasses.replace(self, **changes)

        def to_dict(self):
            return dataclasses.asdict(self)

        @classmethod
        def from_dict(cls, d):
            names = {f.name for f in dataclasses.fields(cls)}
            unknown = sorted(set(d) - names)
            if unknown:
                raise ValueError(f"unknown setting {unknown[0]!r}; known: {', '.join(sorted(names))}")
            return cls(**d).validate()

        def validate(self):
            if not (isinstance(self.voxel_size, (int, float)) and math.isfinite(self.voxel_size) and self.voxel_size > 0):
                raise ValueError(f"voxel_size must be a finite number of mm > 0, got {self.voxel_size!r}")
            for name in ("threshold", "color_threshold"):
                v = getattr(self, name)
                if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                    raise ValueError(f"{name} must be None (automatic) or a finite number > 0, got {v!r}")
            if self.method not in METHODS:
                raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
            if self.hull not in HULL_METHODS:
                raise ValueError(f"hull must be one of {HULL_METHODS}, got {self.hull!r}")
            if not isinstance(self.tolerance, int) or self.tolerance < 0:
                raise ValueError(f"tolerance must be an integer >= 0, got {self.tolerance!r}")
            return self

    class Engine:
        def __init__(self, session, *, calibration=None, recalibrate=False, images=None):
            self.session, self.calibration = session, calibration

        def run(self, settings, *, on_stage=None, cancel=None, until=None):
            kw = settings.to_dict()
            kw.pop("roi")
            return reconstruct(self.session, calibration=self.calibration, **kw)
