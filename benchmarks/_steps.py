"""The default ``organlab reconstruct`` in this process, step by step: time, CPU and peak memory of each step.

Run as a script (a new process, as a user runs the command)::

    PYTHONPATH=$PWD .venv/bin/python benchmarks/_steps.py SESSION OUT VOXEL_MM [--tracemalloc]

It prints one line ``STEPS {json}``: for each step (in the order they ran) its wall and CPU
seconds (all threads), the process's peak resident set during it (VmHWM, reset through
``/proc/self/clear_refs`` when it starts) and what that peak adds to the resident set it started
from, and with ``--tracemalloc`` the peak of the Python allocations during it (numpy's arrays
included; tracing slows the run, so its times are not the command's).

The steps are the stage functions the engine calls, wrapped where ``organlab.engine`` (and the
CLI) look them up: nothing of organlab is changed.  ``imports`` is the import of the CLI module and the engine;
``start-up`` the interpreter's own start (measured by the caller: the process's wall time minus
this script's); ``other`` what no step covers.
"""

from __future__ import annotations

import json
import sys
import threading
import time

T_START = time.perf_counter()
C_START = time.process_time()


def _status(key):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _reset_peak():
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


class Steps:
    def __init__(self, trace):
        self.rows = []
        self.trace = trace
        self.local = threading.local()  # the nesting depth, per thread

    def run(self, name, fn, *args, **kwargs):
        depth = getattr(self.local, "depth", 0)
        if depth:  # a wrapped step inside another: counted in the outer one
            return fn(*args, **kwargs)
        if threading.current_thread().name == "organlab-load":  # the command's loading thread warming a stage
            return fn(*args, **kwargs)  # (a tiny call, not the stage): its CPU stays in the step it overlaps
        if threading.current_thread() is not threading.main_thread():
            return self._beside(name, fn, *args, **kwargs)
        self.local.depth = depth + 1
        try:
            if self.trace:
                import tracemalloc

                tracemalloc.reset_peak()
                tm0 = tracemalloc.get_traced_memory()[0]
            _reset_peak()
            rss0 = _status("VmRSS")
            c0, t0 = time.process_time(), time.perf_counter()
            out = fn(*args, **kwargs)
            t1 = time.perf_counter()
            wall, cpu = t1 - t0, time.process_time() - c0
            peak = _status("VmHWM")
            row = {"step": name, "wall": wall, "cpu": cpu, "peak_mb": peak, "added_mb": peak - rss0, "t": (t0, t1)}
            if self.trace:
                row["traced_peak_mb"] = (tracemalloc.get_traced_memory()[1] - tm0) / 1e6
            self.rows.append(row)
            return out
        finally:
            self.local.depth = depth

    def _beside(self, name, fn, *args, **kwargs):
        """A step the engine runs in a second thread (the AAA measures beside finishing): its own thread's
        CPU and its wall; that CPU is taken off the main thread's step it overlapped (process CPU counts
        both), and its wall is not added to the command's (it overlapped)."""
        self.local.depth = 1
        try:
            c0, t0 = time.thread_time(), time.perf_counter()
            out = fn(*args, **kwargs)
            t1 = time.perf_counter()
            self.rows.append({"step": name, "wall": t1 - t0, "cpu": time.thread_time() - c0,
                              "peak_mb": _status("VmHWM"), "added_mb": float("nan"), "t": (t0, t1), "beside": True})
            return out
        finally:
            self.local.depth = 0

    def wrap(self, owner, attr, name):
        fn = getattr(owner, attr)

        def wrapped(*args, **kwargs):
            return self.run(name, fn, *args, **kwargs)

        setattr(owner, attr, wrapped)


def main():
    session, out, vs = sys.argv[1], sys.argv[2], sys.argv[3]
    trace = "--tracemalloc" in sys.argv
    if trace:
        import tracemalloc

        tracemalloc.start()
    steps = Steps(trace)
    # the CLI module and the engine it runs (imported by the command's first resolve): every import before the run
    mod = steps.run("imports", lambda: (__import__("organlab.engine"), __import__("organlab.cli", fromlist=["main"]))[1])
    from organlab import cli, engine

    for attr, name in [
        ("load_session", "session load"),
        ("check_grid_memory", "preflight"),
        ("check_image_memory", "preflight"),
        ("calibration_for", "calibration load"),
        ("refine_poses", "poses"),
        ("hull_field", "hull field"),
        ("mesh_from_field", "marching cubes"),
        ("finish_surface", "finishing"),
        ("measure_aaa", "AAA measures"),
        ("view_agreement", "agreement"),
        ("hull_masks", "hull masks"),
        ("_report", "report"),
        ("model_warnings", "model checks"),
    ]:
        steps.wrap(engine, attr, name)
    # the command loads it, the stages' first kernels loading on a thread meanwhile (their CPU counted here)
    steps.wrap(cli, "_load_session", "session load")
    steps.wrap(engine.Engine, "_run_silhouettes", "silhouettes")
    steps.wrap(engine.Engine, "_angle_suggestions", "report")
    steps.wrap(engine.BandField, "occupancy", "occupancy")
    steps.wrap(engine.Reconstruction, "save", "writing outputs")
    steps.wrap(cli, "summary_table", "printing")
    c0, t0 = time.process_time(), time.perf_counter()
    code = mod.main(["reconstruct", session, "--out", out, "--voxel-size", vs])
    command = {"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0}
    wall, cpu = time.perf_counter() - T_START, time.process_time() - C_START
    rows = steps.rows
    for b in [r for r in rows if r.get("beside")]:  # its CPU off the main-thread step it overlapped most
        over = [(min(r["t"][1], b["t"][1]) - max(r["t"][0], b["t"][0]), r) for r in rows if not r.get("beside")]
        if over and max(o for o, _ in over) > 0:
            host = max(over, key=lambda o: o[0])[1]
            host["cpu"] = max(0.0, host["cpu"] - b["cpu"])
    rows = [{k: v for k, v in r.items() if k != "t"} for r in rows]
    merged = {}
    for r in rows:  # a step called more than once (preflight, report): one row, times summed, peak max
        m = merged.setdefault(r["step"], {**r, "wall": 0.0, "cpu": 0.0, "peak_mb": 0.0, "added_mb": 0.0})
        m["wall"] += r["wall"]
        m["cpu"] += r["cpu"]
        m["peak_mb"] = max(m["peak_mb"], r["peak_mb"])
        m["added_mb"] = max(m["added_mb"], r["added_mb"])
        if "traced_peak_mb" in r:
            m["traced_peak_mb"] = max(m.get("traced_peak_mb", 0.0), r["traced_peak_mb"])
    rows = list(merged.values())
    inner = sum(r["wall"] for r in rows if r["step"] != "imports" and not r.get("beside"))
    rows.append({"step": "other", "wall": command["wall"] - inner,
                 "cpu": command["cpu"] - sum(r["cpu"] for r in rows if r["step"] != "imports"),
                 "peak_mb": float("nan"), "added_mb": float("nan")})
    peak = max([_status("VmHWM")] + [r["peak_mb"] for r in rows])  # VmHWM was reset at each step
    print("STEPS", json.dumps({"code": code, "wall": wall, "cpu": cpu, "peak_mb": peak, "steps": rows}))
    cli._exit_now(0)  # as the `organlab` program ends: no interpreter teardown (its cost is in "start-up")


if __name__ == "__main__":
    main()
