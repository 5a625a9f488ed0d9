"""Time and peak memory of the reconstruction stages at 2, 1, 0.5 and 0.25 mm.

The bundled sample session ``sample_sessions/aaa_phantom`` (36 views of
640 x 480 px JPEG): cameras from its ``calibration.json``, or calibrated in
memory from its board images when that file is missing (as
:func:`organlab.pipeline.reconstruct` does; not timed).  The stages, as
``reconstruct`` runs them with ``hull='subvoxel'``:

* ``read``: decoding the 36 view images;
* ``silhouettes``: :func:`organlab.silhouette.silhouettes` on the
  decoded images (background frames read, background model, subtraction,
  Li's threshold per view, clean-up, coverage);
* ``rethreshold``: :meth:`organlab.silhouette.SilhouetteModel.silhouettes`
  with a new threshold on already prepared views (what the viewer and the
  threshold widget do on a slider move); the median over 4 thresholds;
* ``hull``: :func:`organlab.carving.hull_field` with ``sparse=True`` (the
  narrow-band field; the voxel size matters only here and below);
* ``surface``: :meth:`organlab.carving.BandField.mesh` (marching cubes on the
  band only) and the occupancy.

Time: best of ``--repeat`` runs after one warm-up (numba compilation and cache
loading excluded; best-of because the machine is shared), wall and CPU (all
threads).  Memory: the process's peak resident set during the stage (VmHWM,
reset before each stage through ``/proc/self/clear_refs``), and what the stage
adds to the resident set it started from.  Growth: the ratio of a stage's time
(and added memory) to that at twice the voxel size; a cost that grows with the
surface gives 4x per halving, one that grows with the volume 8x.

Usage::

    .venv/bin/python benchmarks/bench_stages.py [--session sample_sessions/aaa_phantom]
        [--voxel-sizes 2 1 0.5 0.25] [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from _common import session_cameras, vm_mb  # benchmarks/_common.py (scripts run from this folder)

ROOT = Path(__file__).resolve().parents[1]



def _reset_peak():
    """Reset VmHWM to the current resident set (Linux >= 4.0); False when not allowed."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def measure(fn, repeat):
    """Run ``fn`` once to warm up, then ``repeat`` times.

    Returns ``(result, best_wall_s, best_cpu_s, peak_MB, added_MB)``.
    """
    fn()
    walls, cpus = [], []
    _reset_peak()
    rss0 = vm_mb("VmRSS")
    result = None
    for _ in range(repeat):
        result = None
        c0, t0 = time.process_time(), time.perf_counter()
        result = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    peak = vm_mb("VmHWM")
    return result, min(walls), min(cpus), peak, peak - rss0


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", default=str(ROOT / "sample_sessions" / "aaa_phantom"))
    ap.add_argument("--voxel-sizes", type=float, nargs="+", default=[2.0, 1.0, 0.5, 0.25])
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()

    from organlab import carving
    from organlab.grid import VoxelGrid
    from organlab.session import load_session
    from organlab.silhouette import SilhouetteModel, silhouettes

    session = load_session(a.session)
    cameras, source = session_cameras(session)
    print(f"session {session.name}: {len(session.views)} views, cameras {source}")
    print(f"time: best of {a.repeat} after a warm-up (shared machine); memory: peak RSS during the stage, "
          f"and what it adds (MB)")
    print(f"load average before: {open('/proc/loadavg').read().split()[:3]}")
    rows = []

    def read():
        return [session.read(v.image, key=f"views[{i}].image") for i, v in enumerate(session.views)]

    images, *r = measure(read, a.repeat)
    rows.append(("read", "-", "-", *r))
    sils, *r = measure(lambda: silhouettes(session, images=images), a.repeat)
    rows.append(("silhouettes", "-", "-", *r))
    model = SilhouetteModel.from_session(session, images=images)
    model.silhouettes()
    times = []
    for t in (12.0, 16.0, 20.0, 24.0):
        _, wall, cpu, peak, added = measure(lambda t=t: model.silhouettes(threshold=t), 1)
        times.append((wall, cpu, peak, added))
    rows.append(("rethreshold", "-", "-", statistics.median(x[0] for x in times),
                 statistics.median(x[1] for x in times), max(x[2] for x in times), max(x[3] for x in times)))
    coverages = [s.coverage for s in sils]
    del sils

    per_voxel = {}
    for vs in a.voxel_sizes:
        grid = VoxelGrid.from_roi(session.roi_min, session.roi_max, vs)
        field, *rh = measure(lambda: carving.hull_field(coverages, cameras, grid, sparse=True), a.repeat)
        mesh, *rs = measure(field.mesh, a.repeat)
        _, *ro = measure(field.occupancy, 1)
        shape = "x".join(map(str, grid.shape))
        rows.append(("hull", f"{vs:g}", f"{shape} ({grid.n_voxels / 1e6:.1f} M)", *rh))
        rows.append(("surface", f"{vs:g}", f"{len(mesh.vertices)} vertices, {mesh.volume / 1e3:.2f} cm3", *rs))
        rows.append(("occupancy", f"{vs:g}", f"band {field.n_band_voxels / 1e6:.2f} M voxels, "
                     f"{field.nbytes / 1e6:.1f} MB", *ro))
        per_voxel[vs] = {"hull": rh, "surface": rs}
        del field, mesh

    w = max(len(r[2]) for r in rows)
    print(f"{'stage':<12} {'voxel':>6}  {'grid / result':<{w}} {'wall s':>8} {'CPU s':>8} {'peak MB':>8} {'added MB':>9}")
    for name, vs, what, wall, cpu, peak, added in rows:
        print(f"{name:<12} {vs:>6}  {what:<{w}} {wall:8.3f} {cpu:8.3f} {peak:8.0f} {added:9.0f}")
    sizes = sorted(per_voxel, reverse=True)
    print("\ngrowth per halving of the voxel (time ratio wall, CPU; added-memory ratio)")
    for a_, b_ in zip(sizes, sizes[1:]):
        for st in ("hull", "surface"):
            ra, rb = per_voxel[a_][st], per_voxel[b_][st]
            mem = f"{rb[3] / ra[3]:5.2f}x added memory" if ra[3] >= 1.0 else "added memory < 1 MB before"
            print(f"  {st:<8} {a_:g} -> {b_:g} mm: {rb[0] / ra[0]:5.2f}x wall, {rb[1] / max(ra[1], 1e-9):5.2f}x CPU, {mem}")
    if 1.0 in per_voxel:
        sil = next(r for r in rows if r[0] == "silhouettes")
        h, s = per_voxel[1.0]["hull"], per_voxel[1.0]["surface"]
        print(f"\n1 mm stages, silhouettes + hull + surface: {sil[3] + h[0] + s[0]:.3f} s wall "
              f"({sil[4] + h[1] + s[1]:.3f} s CPU)")


if __name__ == "__main__":
    main()
