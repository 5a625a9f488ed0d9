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
  band only) and the occupancy;
* ``finish``: :func:`organlab.surface.finish_surface` of that mesh (repair,
  smoothing, folds, isotropic remeshing; the cameras' pixel footprint as its
  shortest edge, as ``reconstruct`` passes it);
* ``aaa``: :func:`organlab.surface.measure_aaa` on the band field;
* ``command``: the whole default ``organlab reconstruct SESSION --out DIR
  --voxel-size VS`` (true cameras: a copy by
  :func:`organlab.synthetic.with_true_cameras`, no calibration) in a new
  process each time, step by step (``benchmarks/_steps.py``: start-up,
  imports, session load, calibration load, silhouettes, poses, hull field,
  marching cubes, finishing, AAA measures, occupancy, agreement, report,
  writing outputs): each step's wall and CPU time and the peak resident set
  during it, best of ``--command-repeat`` by CPU time; and, interleaved with those runs, the
  real program (``python -m organlab reconstruct``, whose stages import on a thread while the
  images decode, which ``_steps.py`` cannot wrap): its wall, CPU and peak resident set.

Time: best of ``--repeat`` runs after one warm-up (numba compilation and cache
loading excluded; best-of because the machine is shared), wall and CPU (all
threads).  Memory: the process's peak resident set during the stage (VmHWM,
reset before each stage through ``/proc/self/clear_refs``), and what the stage
adds to the resident set it started from.  Growth: the ratio of a stage's time
(and added memory) to that at twice the voxel size; a cost that grows with the
surface gives 4x per halving, one that grows with the volume 8x.

The last lines (``WHOLE COMMAND``) give the whole process at each voxel size: wall, CPU (all
threads, the interpreter's start included: the parent's rusage of the child) and peak resident
set, against issue 24's targets.  ``--command-only`` runs that part alone (the figures the
issue's targets are about), e.g. best of 3 at 1 and 0.25 mm::

    .venv/bin/python benchmarks/bench_stages.py --command-only --voxel-sizes 1 0.25 --command-repeat 3

Usage::

    .venv/bin/python benchmarks/bench_stages.py [--session sample_sessions/aaa_phantom]
        [--voxel-sizes 2 1 0.5 0.25] [--repeat 3] [--command-repeat 1] [--no-command] [--command-only]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import session_cameras, vm_mb  # benchmarks/_common.py (scripts run from this folder)

ROOT = Path(__file__).resolve().parents[1]

STEPS = Path(__file__).resolve().parent / "_steps.py"  # the whole command, step by step, in a new process


def run_command(session_dir, vs, repeat):
    """Best-of-``repeat`` figures of ``organlab reconstruct`` in a new process, step by step (benchmarks/_steps.py).

    Returns a dict: ``wall`` (the process, start-up included), ``cpu`` (the script's process
    time), ``peak_mb`` and ``steps`` (step -> its row of the best run, by CPU time: the
    machine is shared, CPU varies less than wall).
    """
    # the modules' bytecode cached, as after a user's first run: an environment with PYTHONDONTWRITEBYTECODE
    # (these sessions' shells) otherwise compiles organlab's 117 modules from source in every run (0.4 s CPU
    # of the 1.2-1.45 s the imports took, issue 24)
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(ROOT / "organlab"), str(STEPS.parent)],
                   check=True, capture_output=True)
    best = program = None
    for _ in range(repeat):
        run = run_program(session_dir, vs)  # the real program, interleaved with the step-by-step runs
        if program is None or run["cpu"] < program["cpu"]:
            program = run
        with tempfile.TemporaryDirectory() as out:
            ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            r = subprocess.run([sys.executable, str(STEPS), str(session_dir), out + "/res", f"{vs:g}"],
                               capture_output=True, text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
            wall = time.perf_counter() - t0
            ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        line = [x for x in r.stdout.splitlines() if x.startswith("STEPS ")]
        if r.returncode or not line:
            raise RuntimeError(f"organlab reconstruct at {vs} mm failed:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}")
        res = json.loads(line[-1][6:])
        res["steps"].insert(0, {"step": "start-up", "wall": wall - res["wall"], "cpu": float("nan"),
                                "peak_mb": float("nan"), "added_mb": float("nan")})
        res["process_wall"] = wall
        # the whole process's CPU (all threads, the interpreter's start included), from the parent's rusage
        res["process_cpu"] = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
        # the steps' peaks (VmHWM is reset at each step, so the child's ru_maxrss is only its last step's)
        res["process_peak_mb"] = res["peak_mb"]
        if best is None or res["process_cpu"] < best["process_cpu"]:
            best = res
    best["steps"] = {r["step"]: r for r in best["steps"]}
    best["program"] = program
    return best


def run_program(session_dir, vs):
    """One run of the real program, ``python -m organlab reconstruct SESSION --out DIR --voxel-size VS``.

    The figure issue 24's target is about: unlike benchmarks/_steps.py (which imports the engine
    before the command to wrap its steps), the program imports the stages on a thread while the
    session's images are decoded, as a user's run does.  Returns ``wall``, ``cpu`` (user + sys of
    that process, all threads, from ``os.wait4``) and ``peak_mb`` (its own ``ru_maxrss``).
    """
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        p = subprocess.Popen([sys.executable, "-m", "organlab", "reconstruct", str(session_dir), "--out", out + "/res",
                              "--voxel-size", f"{vs:g}"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                             cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
        err = p.stderr.read()
        _, status, ru = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode:
        raise RuntimeError(f"organlab reconstruct at {vs} mm failed:\n{err.decode(errors='replace')[-2000:]}")
    return {"wall": wall, "cpu": ru.ru_utime + ru.ru_stime, "peak_mb": ru.ru_maxrss / 1024.0}


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


def print_whole(commands, repeat):
    """The whole command's figures, one line per voxel size, and issue 24's targets against them."""
    print(f"\nWHOLE COMMAND `organlab reconstruct SESSION --out DIR --voxel-size VS` (true cameras, calibration given; "
          f"a new process each, best of {repeat} by CPU)")
    print(f"{'voxel':>7} {'wall s':>8} {'CPU s':>8} {'peak MB':>8}   largest steps (CPU s)")
    for vs, c in commands.items():
        top = sorted(((r["cpu"], n) for n, r in c["steps"].items() if r["cpu"] == r["cpu"]), reverse=True)[:5]
        print(f"{vs:>5g} mm {c['process_wall']:8.2f} {c['process_cpu']:8.2f} {c['process_peak_mb']:8.0f}   "
              + ", ".join(f"{n} {t:.2f}" for t, n in top))
        g = c["program"]
        print(f"{'':>8} {g['wall']:8.2f} {g['cpu']:8.2f} {g['peak_mb']:8.0f}   the program itself "
              "(python -m organlab reconstruct: the stages imported while the images decode)")
    targets = {1.0: (3.0, None), 0.25: (20.0, 1000.0)}
    for vs, (sec, mb) in targets.items():
        if vs in commands:
            c = commands[vs]
            what = f"{vs:g} mm: target under {sec:g} s" + (f" and {mb:g} MB" if mb else "")
            g = c["program"]
            print(f"  issue 24, {what}: the program: wall {g['wall']:.2f} s, CPU {g['cpu']:.2f} s, "
                  f"peak {g['peak_mb']:.0f} MB; "
                  f"step by step: wall {c['process_wall']:.2f} s, CPU {c['process_cpu']:.2f} s, "
                  f"peak {c['process_peak_mb']:.0f} MB (on a shared machine read the CPU; on a quiet one the wall)")
    print(f"load average after: {open('/proc/loadavg').read().split()[:3]}")


def command_only(a):
    """``--command-only``: the whole default command at each voxel size, step by step, and its summary."""
    from organlab.synthetic import with_true_cameras

    print(f"load average before: {open('/proc/loadavg').read().split()[:3]}")
    commands = {}
    with tempfile.TemporaryDirectory() as tmp:
        true_session = with_true_cameras(a.session, Path(tmp) / "session")
        for vs in a.voxel_sizes:
            commands[vs] = run_command(true_session, vs, a.command_repeat)
    print_steps(commands, a.command_repeat)
    print_whole(commands, a.command_repeat)


def print_steps(commands, repeat):
    """Each step's wall s / CPU s / peak MB at each voxel size, and their growth per halving."""
    vss = list(commands)
    print(f"\nwhole default command (organlab reconstruct, true cameras, a new process each; best of "
          f"{repeat} by CPU): per step wall s / CPU s / peak MB (VmHWM during the step); a step marked * ran in a "
          f"second thread beside another step (its wall overlapped; its CPU is its thread's, taken off the other's)")
    names = list(dict.fromkeys(k for c in commands.values() for k in c["steps"]))
    print(f"{'step':<18}" + "".join(f"{f'{vs:g} mm':>26}" for vs in vss))
    for n in names:
        cells = []
        for vs in vss:
            r = commands[vs]["steps"].get(n)
            cells.append(" " * 26 if r is None else f"{r['wall']:8.2f} {r['cpu']:7.2f} {r['peak_mb']:8.0f}"
                         + ("* " if r.get("beside") else "  "))
        print(f"{n:<18}" + "".join(cells))
    print(f"{'whole process':<18}" + "".join(f"{c['process_wall']:8.2f} {c['process_cpu']:7.2f} "
                                             f"{c['process_peak_mb']:8.0f}  " for c in commands.values()))
    print("growth per halving of the voxel (CPU ratio; whole process: wall and peak ratios)")
    for a_, b_ in zip(vss, vss[1:]):
        ca, cb = commands[a_], commands[b_]
        grow = [f"{n} {cb['steps'][n]['cpu'] / ca['steps'][n]['cpu']:.2f}x" for n in names
                if n in ca["steps"] and n in cb["steps"] and ca["steps"][n]["cpu"] >= 0.005]
        print(f"  {a_:g} -> {b_:g} mm: whole {cb['process_wall'] / ca['process_wall']:.2f}x wall, "
              f"{cb['peak_mb'] / ca['peak_mb']:.2f}x peak; " + ", ".join(grow))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", default=str(ROOT / "sample_sessions" / "aaa_phantom"))
    ap.add_argument("--voxel-sizes", type=float, nargs="+", default=[2.0, 1.0, 0.5, 0.25])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--command-repeat", type=int, default=1, help="runs of the whole command per voxel size")
    ap.add_argument("--no-command", action="store_true", help="skip the whole command")
    ap.add_argument("--command-only", action="store_true",
                    help="only the whole command (no in-process stage timings): the issue-24 figures alone")
    a = ap.parse_args()
    if a.command_only:
        return command_only(a)

    from organlab import carving
    from organlab.grid import VoxelGrid
    from organlab.pipeline import pixel_footprint
    from organlab.session import load_session
    from organlab.silhouette import SilhouetteModel, silhouettes
    from organlab.surface import finish_surface, measure_aaa, mesh_from_field

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
        mesh, *rs = measure(lambda: mesh_from_field(field, grid), a.repeat)
        _, *ro = measure(field.occupancy, 1)
        foot = pixel_footprint(cameras, grid)
        (fin, rep), *rf = measure(lambda: finish_surface(mesh, voxel_size=vs, min_edge_mm=foot), a.repeat)
        aaa, *ra = measure(lambda: measure_aaa(field, grid), a.repeat)
        shape = "x".join(map(str, grid.shape))
        rows.append(("hull", f"{vs:g}", f"{shape} ({grid.n_voxels / 1e6:.1f} M)", *rh))
        rows.append(("surface", f"{vs:g}", f"{len(mesh.faces)} faces, {mesh.volume / 1e3:.2f} cm3", *rs))
        rows.append(("occupancy", f"{vs:g}", f"band {field.n_band_voxels / 1e6:.2f} M voxels, "
                     f"{field.nbytes / 1e6:.1f} MB", *ro))
        q = rep["final"]
        rows.append(("finish", f"{vs:g}", f"{q['faces']} faces, {q['min_angle_deg']:.1f} deg, "
                     f"{'closed' if rep['watertight'] else 'OPEN'}, {q['volume_mm3'] / 1e3:.2f} cm3", *rf))
        rows.append(("aaa", f"{vs:g}", f"max diameter {aaa.max_diameter_mm:.1f} mm, "
                     f"{len(aaa.arc_mm)} sections", *ra))
        per_voxel[vs] = {"hull": rh, "surface": rs, "finish": rf, "aaa": ra}
        del field, mesh, fin, aaa

    commands = {}
    if not a.no_command:
        from organlab.synthetic import with_true_cameras

        with tempfile.TemporaryDirectory() as tmp:
            true_session = with_true_cameras(a.session, Path(tmp) / "session")
            for vs in a.voxel_sizes:
                commands[vs] = run_command(true_session, vs, a.command_repeat)

    w = max(len(r[2]) for r in rows)
    print(f"{'stage':<12} {'voxel':>6}  {'grid / result':<{w}} {'wall s':>8} {'CPU s':>8} {'peak MB':>8} {'added MB':>9}")
    for name, vs, what, wall, cpu, peak, added in rows:
        print(f"{name:<12} {vs:>6}  {what:<{w}} {wall:8.3f} {cpu:8.3f} {peak:8.0f} {added:9.0f}")
    sizes = sorted(per_voxel, reverse=True)
    print("\ngrowth per halving of the voxel (time ratio wall, CPU; added-memory ratio)")
    for a_, b_ in zip(sizes, sizes[1:]):
        for st in ("hull", "surface", "finish", "aaa"):
            ra, rb = per_voxel[a_][st], per_voxel[b_][st]
            mem = f"{rb[3] / ra[3]:5.2f}x added memory" if ra[3] >= 1.0 else "added memory < 1 MB before"
            print(f"  {st:<8} {a_:g} -> {b_:g} mm: {rb[0] / ra[0]:5.2f}x wall, {rb[1] / max(ra[1], 1e-9):5.2f}x CPU, {mem}")
    if commands:
        print_steps(commands, a.command_repeat)
    if 1.0 in per_voxel:
        sil = next(r for r in rows if r[0] == "silhouettes")
        st = [per_voxel[1.0][k] for k in ("hull", "surface", "finish", "aaa")]
        print(f"\n1 mm stages, silhouettes + hull + surface + finish + aaa: {sil[3] + sum(x[0] for x in st):.3f} s wall "
              f"({sil[4] + sum(x[1] for x in st):.3f} s CPU)")
    if commands:
        print_whole(commands, a.command_repeat)


if __name__ == "__main__":
    main()
