"""A 12-setting sweep of the sample session: a LocalCluster of worker processes against the serial fallback.

The sweep: thresholds 10, 15, ..., 35 grey levels x methods hull and coloring at 2 mm (the default
finished surface and AAA measures), i.e. 6 tasks of 2 settings that share their silhouettes and
carving.  Both runs use one calibration, computed before (not timed), so their results can be
compared bit for bit (they are: checked at the end).

Timed: ``organlab.batch.sweep`` with ``workers=0`` (in this process, one numba thread, as every
task runs) and with a running ``LocalCluster`` of ``--workers`` processes (one thread each).  Both
are warmed first (numba's kernels loaded from its cache, in this process and in every worker), so
the ratio compares the sweeps, not start-up; the cluster's start-up is printed apart.  The machine
may be shared: serial and parallel runs alternate (``--repeat`` pairs, default 3; the best wall
time of each is kept), the 1-minute load average before and after each run is printed with it,
and so is the CPU time (user + sys) of this process and of each worker: the busiest worker's CPU
against the serial run's is what the ratio would be with a core for each worker.

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


def _cpu():
    """CPU time (user + sys) of this process, every thread, s."""
    t = os.times()
    return t.user + t.system


def _cpu_of(client):
    """CPU time of each worker process (user + sys), s; {} without a client."""
    return {} if client is None else dict(client.run(_cpu))


def _timed(label, fn, client=None):
    """One run of ``fn``: wall time, CPU of this process and of each worker, load average before and after."""
    before, c0, w0 = _load(), _cpu(), _cpu_of(client)
    t0 = time.perf_counter()
    out = fn()
    t = time.perf_counter() - t0
    c, w = _cpu() - c0, {k: v - w0[k] for k, v in _cpu_of(client).items() if k in w0}
    workers = f", workers {' + '.join(f'{v:.1f}' for v in w.values())} s" if w else ""
    print(f"  {label:<28} {t:7.1f} s wall   CPU: this process {c:.1f} s{workers}   (load {before:.1f}->{_load():.1f})",
          flush=True)
    return {"wall": t, "cpu": c, "workers": w}, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
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
    groups = ob.plan_leaves(ob.plan_tasks(ob.expand(GRID, ob.Settings(**settings))), n_workers=a.workers)
    tasks = [t for g in groups for t in g]
    print(f"bench_sweep: {session.name}, {n} settings ({' x '.join(f'{len(v)} {k}' for k, v in GRID.items())}) at "
          f"{a.voxel_size:g} mm, {len(tasks)} tasks after {len(groups)} shared first stages; {os.cpu_count()} CPU cores, load average {_load():.1f}")
    tmp = Path(tempfile.mkdtemp(prefix="bench_sweep-"))
    try:
        _warm()

        def serial():
            out = tmp / "serial"
            shutil.rmtree(out, ignore_errors=True)
            return ob.sweep(session, GRID, settings=settings, out=out, calibration=cal, workers=0, plots=False)

        runs = {"serial": [], "parallel": []}
        t0 = time.perf_counter()
        with ob.dask_client(workers=a.workers) as client:
            t_start = time.perf_counter() - t0
            client.run(_warm)
            print(f"  {'cluster start-up':<28} {t_start:7.1f} s   ({a.workers} worker processes, then warmed)")

            def parallel():
                out = tmp / "parallel"
                shutil.rmtree(out, ignore_errors=True)
                return ob.sweep(session, GRID, settings=settings, out=out, calibration=cal, client=client, plots=False)

            for _ in range(a.repeat):  # interleaved: both see the same load
                r, ref = _timed("serial (workers=0)", serial)
                runs["serial"].append(r)
                r, df = _timed(f"LocalCluster ({a.workers} workers)", parallel, client)
                runs["parallel"].append(r)
        best = {k: min(v, key=lambda r: r["wall"]) for k, v in runs.items()}
        t_serial, t_par = best["serial"]["wall"], best["parallel"]["wall"]
        cpu_serial = min(r["cpu"] for r in runs["serial"])
        cpu_workers = min(max(r["workers"].values()) for r in runs["parallel"])
        cpu_client = min(r["cpu"] for r in runs["parallel"])
        print(f"  best of {a.repeat}: serial {t_serial:.1f} s, parallel {t_par:.1f} s wall; CPU: serial {cpu_serial:.1f} s, "
              f"busiest worker {cpu_workers:.1f} s (both {min(sum(r['workers'].values()) for r in runs['parallel']):.1f} s), "
              f"client {cpu_client:.1f} s")
        print(f"  CPU-bound estimate for an idle machine (busiest worker's CPU / serial CPU): {cpu_workers / cpu_serial:.2f}")
        cols = ["volume_mm3", "mesh_volume_mm3", "agreement_mean_iou", "agreement_worst_iou"]
        same = all(np.array_equal(df[c].to_numpy(), ref[c].to_numpy()) for c in cols)
        for name in df["name"]:
            for f in ("mesh.ply", "voxels.npz"):
                same &= (tmp / "parallel" / "results" / name / f).read_bytes() == (tmp / "serial" / "results" / name / f).read_bytes()
        pairs = [p["wall"] / q["wall"] for p, q in zip(runs["parallel"], runs["serial"])]
        print(f"  parallel / serial            {t_par / t_serial:7.2f}    (target <= 0.65; best walls); each pair "
              f"{', '.join(f'{x:.2f}' for x in pairs)}; results identical: {same}")
        print(f"  per setting: serial {t_serial / n:.1f} s, parallel {t_par / n:.1f} s; "
              f"sum of the settings' own times {ref['seconds'].sum():.1f} s serial, {df['seconds'].sum():.1f} s on the workers")
        rec = df.attrs["recommended"]
        print(f"  recommended: {rec['name']}: {rec['reason']}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
