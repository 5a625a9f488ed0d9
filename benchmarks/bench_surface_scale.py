"""Time and peak memory of the surface stage's steps at 1, 0.5 and 0.25 mm, before/after.

The bundled sample session reconstructed with ``finish=False, measure=False``
(the hull's band field and the raw marching-cubes mesh), then, in this
process, each step of the default surface stage with peak RSS (VmHWM) reset
through ``/proc/self/clear_refs`` before it:

* ``repair``, ``smooth``: :func:`organlab.surface.repair_mesh`, ``smooth_mesh``;
* ``remesh``: ``remesh_mesh`` at the old automatic edge (1.5 voxels, up to 3
  passes while the smallest angle is below 20 degrees: the baseline) and at the
  new one (``max(1.5 voxels, 0.75 mm)``, passes stop when one gains < 1 degree);
* ``aaa``: :func:`organlab.surface.measure_aaa` on the densified field with the
  old settings (``centreline_voxel_mm`` = the voxel, pixel = half a voxel:
  the baseline) and on the band field with the defaults.

Prints each figure and the new/old ratios, and the AAA measures of both
paths.  Usage::

    .venv/bin/python benchmarks/bench_surface_scale.py [--voxel-sizes 1 0.5 0.25]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from _common import vm_mb  # benchmarks/_common.py (scripts run from this folder)

ROOT = Path(__file__).resolve().parents[1]


def _run(fn):
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass
    r0, t0 = vm_mb("VmRSS"), time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0, vm_mb("VmHWM") - r0


def _old_remesh(mesh, target):
    """The remeshing as it was: up to 3 passes while the smallest angle is below 20 degrees."""
    import pymeshlab

    from organlab.surface import mesh_quality
    from organlab.surface._repair import _from_ms, _to_ms

    ms = _to_ms(mesh)
    for _ in range(3):
        ms.meshing_isotropic_explicit_remeshing(targetlen=pymeshlab.PureValue(target), iterations=10, featuredeg=60.0)
        if mesh_quality(_from_ms(ms))["min_angle_deg"] >= 20.0:
            break
    return _from_ms(ms)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", default=str(ROOT / "sample_sessions" / "aaa_phantom"))
    ap.add_argument("--voxel-sizes", type=float, nargs="+", default=[1.0, 0.5, 0.25])
    a = ap.parse_args()

    from organlab.pipeline import reconstruct
    from organlab.surface import measure_aaa, mesh_quality, remesh_mesh, repair_mesh, smooth_mesh

    print(f"load average before: {open('/proc/loadavg').read().split()[:3]}")
    print(f"{'voxel':>6} {'step':<22} {'wall s':>8} {'added MB':>9}  result")
    for vs in a.voxel_sizes:
        rec = reconstruct(a.session, voxel_size=vs, finish=False, measure=False)
        raw = rec.raw_mesh
        (m1, _), t, mb = _run(lambda: repair_mesh(raw, speck_mm=3 * vs))
        print(f"{vs:6g} {'repair':<22} {t:8.2f} {mb:9.0f}  {len(raw.faces)} -> {len(m1.faces)} faces")
        (m2, _), t, mb = _run(lambda: smooth_mesh(m1))
        print(f"{vs:6g} {'smooth':<22} {t:8.2f} {mb:9.0f}")
        figs = {}
        for name, fn in (("remesh old", lambda: _old_remesh(m2, 1.5 * vs)),
                         ("remesh new", lambda: remesh_mesh(m2, max(1.5 * vs, 0.75))[0])):
            m3, t, mb = _run(fn)
            q = mesh_quality(m3)
            figs[name] = (t, mb)
            print(f"{vs:6g} {name:<22} {t:8.2f} {mb:9.0f}  {q['faces']} faces, smallest angle {q['min_angle_deg']:.1f} deg")
        old_aaa = lambda: measure_aaa(np.asarray(rec.field), rec.grid, centreline_voxel_mm=vs, pixel_mm=0.5 * vs)
        for name, fn in (("aaa old (dense)", old_aaa), ("aaa new (band)", lambda: measure_aaa(rec.field, rec.grid))):
            m, t, mb = _run(fn)
            figs[name] = (t, mb)
            print(f"{vs:6g} {name:<22} {t:8.2f} {mb:9.0f}  max {m.max_diameter_mm:.3f} mm, neck "
                  f"{m.neck_diameter_mm:.3f} mm, sac {m.sac_volume_mm3 / 1e3:.2f} cm3, {m.sac_length_mm:.2f} mm")
        for st in ("remesh", "aaa"):
            o, n = [v for k, v in figs.items() if k.startswith(st)]
            print(f"{vs:6g} {st + ' new/old':<22} {n[0] / o[0]:8.2f}x {n[1] / max(o[1], 1.0):8.2f}x")
        del rec, raw, m1, m2


if __name__ == "__main__":
    main()
