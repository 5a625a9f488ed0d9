"""A 12-setting sweep of the sample session: a LocalCluster of worker processes against the serial fallback.

The sweep: thresholds 10, 15, ..., 35 grey levels x methods hull and coloring at 2 mm (the default
finished surface and AAA measures), i.e. 6 tasks of 2 settings that share their silhouettes and
carving.  Both runs use one calibration, computed before (not timed), so their results can be
compared bit for bit (they are: checked at the end).

Timed: ``organlab.batch.sweep`` with ``workers=0`` (in this process, one numba thread, as every
task runs) and with a running ``LocalCluster`` of ``--workers`` processes (one thread each).  Both
are warmed first (numba's kernels loaded from its cache, in this process and in every worker), so
the ratio compares the sweeps, not start-up; the cluster's start-up is printed apart.  The machine
may be shared: the 1-minute load average before and after each run is printed with it, and
``--repeat`` keeps the best of several runs of each.

Usage::

    .venv/bin/python benchmarks/bench_sweep.py [--workers 2] [--repeat 1] [--voxel-size 2]
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_sessions" / "aaa_phantom"
GRID = {"threshold": [10.0, 15.0, 20.0, 25.0, 30.0, 35.0], "method": ["hull", "coloring"]}


def _warm():
    """Load numba's compiled kernels in this process (a tiny reconstruction at 8 mm)."""
    from organlab.engine import Engine, Settings

    Engine(str(SAMPLE)).run(Settings(voxel_size=8.0, method="coloring", finish=False, measure=False))
    return os.getpid()


def _load():
    return os.getloadavg()[0]


def _timed(label, fn, repeat):
    best, loads = None, []
    for _ in range(repeat):
        before = _load()
        t0 = time.perf_counter()
        out = fn()
        t = time.perf_counter() - t0
        loads.append((before, _load()))
        best = t if best is None or t < best else best
    print(f"  {label:<28} {best:7.1f} s   (load average {', '.join(f'{a:.1f}->{b:.1f}' for a, b in loads)})", flush=True)
    return best, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--voxel-size", type=float, default=2.0)
    a = ap.parse_args(argv)

    import numpy as np

    import organlab.batch as ob
    from organlab.calibration import calibration_for
    from organlab.session import load_session

    session = load_session(SAMPLE)
    cal = calibration_for(session)[0]
    settings = {"voxel_size": a.voxel_size}
    n = len(ob.expand(GRID, ob.Settings(**settings)))
    tasks = ob.plan_tasks(ob.expand(GRID, ob.Settings(**settings)), n_workers=a.workers)
    print(f"bench_sweep: {session.name}, {n} settings ({' x '.join(f'{len(v)} {k}' for k, v in GRID.items())}) at "
          f"{a.voxel_size:g} mm, {len(tasks)} tasks; {os.cpu_count()} CPU cores, load average {_load():.1f}")
    tmp = Path(tempfile.mkdtemp(prefix="bench_sweep-"))
    try:
        _warm()

        def serial():
            out = tmp / "serial"
            shutil.rmtree(out, ignore_errors=True)
            return ob.sweep(session, GRID, settings=settings, out=out, calibration=cal, workers=0, plots=False)

        t_serial, ref = _timed("serial (workers=0)", serial, a.repeat)
        t0 = time.perf_counter()
        with ob.dask_client(workers=a.workers) as client:
            t_start = time.perf_counter() - t0
            client.run(_warm)
            print(f"  {'cluster start-up':<28} {t_start:7.1f} s   ({a.workers} worker processes, then warmed)")

            def parallel():
                out = tmp / "parallel"
                shutil.rmtree(out, ignore_errors=True)
                return ob.sweep(session, GRID, settings=settings, out=out, calibration=cal, client=client, plots=False)

            t_par, df = _timed(f"LocalCluster ({a.workers} workers)", parallel, a.repeat)
        cols = ["volume_mm3", "mesh_volume_mm3", "agreement_mean_iou", "agreement_worst_iou"]
        same = all(np.array_equal(df[c].to_numpy(), ref[c].to_numpy()) for c in cols)
        for name in df["name"]:
            for f in ("mesh.ply", "voxels.npz"):
                same &= (tmp / "parallel" / "results" / name / f).read_bytes() == (tmp / "serial" / "results" / name / f).read_bytes()
        print(f"  parallel / serial            {t_par / t_serial:7.2f}    (target <= 0.65); results identical: {same}")
        print(f"  per setting: serial {t_serial / n:.1f} s, parallel {t_par / n:.1f} s; "
              f"sum of the settings' own times {ref['seconds'].sum():.1f} s serial, {df['seconds'].sum():.1f} s on the workers")
        rec = df.attrs["recommended"]
        print(f"  recommended: {rec['name']}: {rec['reason']}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
