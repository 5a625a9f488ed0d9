"""A 12-setting sweep of the sample session: a LocalCluster of worker processes against the serial fallback.

The sweep: thresholds 10, 15, ..., 35 grey levels x methods hull and coloring at 2 mm (the default
finished surface and AAA measures): 6 shared-prefix tasks (a threshold's silhouettes, poses and
carving) and 12 tasks that go on from them, one per setting.  Both runs use one calibration,
computed before (not timed), so their results can be compared bit for bit (they are: checked at
the end).

Timed: ``organlab.batch.sweep`` with ``workers=0`` (in this process, one numba thread, as every
task runs) and with a running ``LocalCluster`` of ``--workers`` processes (one thread each).  Both
are warmed first (numba's kernels loaded from its cache, in this process and in every worker), so
the ratio compares the sweeps, not start-up; the cluster's start-up is printed apart.  The machine
may be shared: serial and parallel runs alternate (``--repeat`` pairs, default 3; the best wall
time of each is kept), the 1-minute load average before and after each run is printed with it,
and so is the CPU time (user + sys) of this process and of each worker: the busiest worker's CPU
against the serial run's is what the ratio would be with a core for each worker and nothing else
running; "in the tasks" is the CPU the tasks measured themselves (``cpu_seconds`` in the table),
the rest of a worker's is Dask's.  The critical path (a threshold's shared stages and its longest
task, in the last parallel run's task stream) and each worker's idle time show how well it was spread.

The last line is the answer: ``RATIO parallel / serial wall = ...`` with the load average during the
runs (the ratio means what it says only on an otherwise idle machine: load below ~0.5 before it starts;
with the kernel's autogroup scheduling, other sessions' load holds the two workers to the one share of
the cores the serial run had, and the ratio tends to 1 whatever the code does: docs/scale.md).
The line before it prints the CPU figures: the serial run's, the workers' (in their tasks and in all),
and the busiest worker's CPU against the serial run's.  About 3-4 minutes on an idle 2-core machine
with the default ``--repeat 3``.

Usage::

    .venv/bin/python benchmarks/bench_sweep.py [--workers 2] [--repeat 3] [--voxel-size 2]
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
    """Load numba's compiled kernels and pymeshlab in this process: a reconstruction at 8 mm with every stage
    the sweep runs (colouring, finished surface, AAA measures), so no run pays a first load."""
    from organlab.engine import Engine, Settings

    Engine(str(SAMPLE)).run(Settings(voxel_size=8.0, method="coloring"))
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
    after = _load()
    in_tasks = float(out["cpu_seconds"].sum()) if "cpu_seconds" in out else float("nan")  # (older organlab: none)
    workers = f", workers {' + '.join(f'{v:.1f}' for v in w.values())} s" if w else ""
    print(f"  {label:<26} {t:7.1f} s wall   CPU: this process {c:.1f} s{workers}, in the tasks {in_tasks:.1f} s"
          f"   (load {before:.1f} -> {after:.1f})", flush=True)
    return {"wall": t, "cpu": c, "workers": w, "in_tasks": in_tasks, "load": (before, after)}, out


def _schedule(stream):
    """The last parallel run's schedule from Dask's task stream (the workers' wall times): each worker's busy
    time and its idle time before the last task ends, and the longest chain (a threshold's shared stages, then
    the longest task that went on from them: a task's prefix is the last one submitted before it)."""
    spans = {}
    for t in stream:
        for ss in t["startstops"]:
            if ss["action"] == "compute":
                spans[t["key"]] = (t["worker"], ss["start"], ss["stop"])
    if not spans:
        return
    t0 = min(a for _, a, _ in spans.values())
    end = max(b for _, _, b in spans.values())
    busy = {}
    for w, a, b in spans.values():
        busy[w] = busy.get(w, 0.0) + b - a
    prefixes = sorted((int(k.split("-")[2]), b - a) for k, (_, a, b) in spans.items() if k.startswith("organlab-prefix-"))
    chains = {}
    for k, (_, a, b) in spans.items():
        if k.startswith("organlab-task-"):
            i = int(k.split("-")[2])
            mine = [p for p in prefixes if p[0] <= i]
            if mine:
                j, shared = mine[-1]
                chains[j] = max(chains.get(j, (0.0, shared))[0], b - a), shared
    idle = ", ".join(f"{end - t0 - v:.1f}" for v in busy.values())
    line = (f"  schedule of the last parallel run (workers' wall time): busy {' + '.join(f'{v:.1f}' for v in busy.values())} s "
            f"in {end - t0:.1f} s (idle {idle} s)")
    if chains:
        task, shared = max(chains.values(), key=lambda c: c[0] + c[1])
        line += (f"; longest chain: shared stages {shared:.1f} s + task {task:.1f} s = {shared + task:.1f} s "
                 f"({(shared + task) / (end - t0):.2f} of the run)")
    print(line)


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
    tasks = [t for _, g in groups for t in g]
    print(f"bench_sweep: {session.name}, {n} settings ({' x '.join(f'{len(v)} {k}' for k, v in GRID.items())}) at "
          f"{a.voxel_size:g} mm, {len(tasks)} tasks after {len(groups)} shared first stages; {os.cpu_count()} CPU cores, "
          f"load average {_load():.1f}", flush=True)
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
            print(f"  {'cluster start-up':<26} {t_start:7.1f} s   ({a.workers} worker processes, then warmed)", flush=True)

            def parallel():
                out = tmp / "parallel"
                shutil.rmtree(out, ignore_errors=True)
                return ob.sweep(session, GRID, settings=settings, out=out, calibration=cal, client=client, plots=False)

            from distributed import get_task_stream

            for _ in range(a.repeat):  # interleaved: both see the same load
                r, ref = _timed("serial (workers=0)", serial)
                runs["serial"].append(r)
                with get_task_stream(client) as ts:
                    r, df = _timed(f"LocalCluster ({a.workers} workers)", parallel, client)
                stream = ts.data
                runs["parallel"].append(r)
        best = {k: min(v, key=lambda r: r["wall"]) for k, v in runs.items()}
        t_serial, t_par = best["serial"]["wall"], best["parallel"]["wall"]
        cpu_serial = min(r["cpu"] for r in runs["serial"])
        busiest = min(max(r["workers"].values()) for r in runs["parallel"])
        both = min(sum(r["workers"].values()) for r in runs["parallel"])
        in_tasks = min(r["in_tasks"] for r in runs["parallel"])
        cpu_client = min(r["cpu"] for r in runs["parallel"])
        loads = [x for k in runs for r in runs[k] for x in r["load"]]
        print(f"  CPU, best of {a.repeat}: serial run {cpu_serial:.1f} s (in its tasks {min(r['in_tasks'] for r in runs['serial']):.1f} s); "
              f"workers {both:.1f} s (in their tasks {in_tasks:.1f} s), busiest worker {busiest:.1f} s; client {cpu_client:.1f} s")
        print(f"  busiest worker's CPU / serial CPU: {busiest / cpu_serial:.2f}   (the wall ratio with a core for each "
              f"worker and nothing else running; ideal 0.5)")
        cols = ["volume_mm3", "mesh_volume_mm3", "agreement_mean_iou", "agreement_worst_iou"]
        same = all(np.array_equal(df[c].to_numpy(), ref[c].to_numpy()) for c in cols)
        for name in df["name"]:
            for f in ("mesh.ply", "voxels.npz"):
                same &= (tmp / "parallel" / "results" / name / f).read_bytes() == (tmp / "serial" / "results" / name / f).read_bytes()
        pairs = [p["wall"] / q["wall"] for p, q in zip(runs["parallel"], runs["serial"])]
        print(f"  per setting: serial {t_serial / n:.1f} s, parallel {t_par / n:.1f} s wall; each pair's ratio "
              f"{', '.join(f'{x:.2f}' for x in pairs)}")
        _schedule(stream)
        rec = df.attrs["recommended"]
        print(f"  recommended: {rec['name']}: {rec['reason']}")
        print(f"RATIO parallel / serial wall = {t_par / t_serial:.2f} (target <= 0.65): best of {a.repeat}, serial "
              f"{t_serial:.1f} s, {a.workers} workers {t_par:.1f} s; load average {min(loads):.1f}-{max(loads):.1f} "
              f"during the runs on {os.cpu_count()} cores (trust it below ~0.5); results identical: {same}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
