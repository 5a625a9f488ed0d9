"""CPU time of :func:`organlab.surface.measure_aaa` on the sample's band field, this code against a
revision's, alternately in one process, and whether their measures are the same bits.

The bundled sample session reconstructed with ``finish=False, measure=False`` at each voxel size
(the hull's band field, what the engine measures), then ``measure_aaa`` of this tree and of
``organlab/surface/_aaa.py`` at ``--against`` (loaded from git beside it, the rest of the package
shared), old and new in turn, ``--repeat`` times each; the process's CPU time (all its threads:
the old sac volume's cKDTree query ran on two; numba on one thread, as on the engine's measuring
thread), best of the repeats, and the ratio.  Every array and scalar of both results is compared bit for bit.  Usage::

    .venv/bin/python benchmarks/bench_aaa.py [--voxel-sizes 1 0.25] [--against REV] [--repeat 3]
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FIELDS = ("centreline", "arc_mm", "feret_mm", "equivalent_mm", "max_index", "max_diameter_mm",
          "max_equivalent_mm", "max_location_mm", "max_section", "neck_diameter_mm", "sac_start_mm",
          "sac_end_mm", "sac_length_mm", "sac_volume_mm3")


def _old_module(rev):
    """``organlab.surface._aaa`` as it was at ``rev``, imported as ``organlab.surface._aaa_at_rev``."""
    src = subprocess.run(["git", "show", f"{rev}:organlab/surface/_aaa.py"], cwd=ROOT, capture_output=True,
                         text=True, check=True).stdout
    path = Path(tempfile.mkdtemp()) / "_aaa_at_rev.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("organlab.surface._aaa_at_rev", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def _cpu(fn, *args):
    t = time.process_time()
    out = fn(*args)
    return out, time.process_time() - t


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--session", default=str(ROOT / "sample_sessions" / "aaa_phantom"))
    ap.add_argument("--voxel-sizes", type=float, nargs="+", default=[1.0, 0.25])
    ap.add_argument("--against", default="dc59702",
                    help="git revision of the old _aaa.py (default: before issue 24's AAA measures work)")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()

    import numba

    from organlab.pipeline import reconstruct
    from organlab.surface import _aaa

    numba.set_num_threads(1)  # as the engine's measuring thread (engine._measure_beside)
    old = _old_module(a.against)
    print(f"measure_aaa, CPU s, best of {a.repeat}, old = {a.against}, alternately")
    print(f"{'voxel mm':>8} {'old':>7} {'new':>7} {'new/old':>7}  same bits")
    for vs in a.voxel_sizes:
        rec = reconstruct(a.session, voxel_size=vs, finish=False, measure=False)
        field, grid = rec.field, rec.grid
        ro, rn = old.measure_aaa(field, grid), _aaa.measure_aaa(field, grid)  # compiles, caches
        to, tn = [], []
        for _ in range(a.repeat):
            ro, t = _cpu(old.measure_aaa, field, grid)
            to.append(t)
            rn, t = _cpu(_aaa.measure_aaa, field, grid)
            tn.append(t)
        diff = [k for k in FIELDS if not np.array_equal(np.asarray(getattr(ro, k)), np.asarray(getattr(rn, k)),
                                                        equal_nan=True)]
        print(f"{vs:8g} {min(to):7.3f} {min(tn):7.3f} {min(tn) / min(to):7.2f}  {'yes' if not diff else diff}")


if __name__ == "__main__":
    main()
