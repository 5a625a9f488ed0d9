"""Benchmark of voxel colouring on the bundled sample session.

``sample_sessions/aaa_phantom`` (36 views, 640 x 480 px, JPEG): cameras from
the session's ``calibration.json`` (as ``organlab calibrate`` writes it), or
calibrated in memory from the session's board images when it is missing (as
:func:`organlab.pipeline.reconstruct` does), silhouettes by background subtraction
(:func:`organlab.silhouette.silhouettes`), visual hull by
:func:`organlab.carving.carve` at 1 mm, then
:func:`organlab.coloring.color_voxels` with its defaults.

Printed: wall-clock and CPU seconds of the colouring call (best of ``--repeat`` runs
after one warm-up run, so numba's compilation or cache loading is
excluded), the process's peak resident memory before and after colouring
(VmHWM, so the difference is what colouring adds on top of the loaded
images, masks and hull), and the volumes of the hull and of the coloured
solid against the session's reference volume.

Usage::

    .venv/bin/python benchmarks/bench_coloring.py [--session sample_sessions/aaa_phantom]
        [--voxel-size 1] [--repeat 3] [--method voxel_coloring]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from _common import session_cameras, vm_mb  # benchmarks/_common.py (scripts run from this folder)

import numpy as np

ROOT = Path(__file__).resolve().parents[1]



def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", default=str(ROOT / "sample_sessions" / "aaa_phantom"))
    ap.add_argument("--voxel-size", type=float, default=1.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--method", default="voxel_coloring", choices=["voxel_coloring", "space_carving"])
    a = ap.parse_args()

    from organlab import carving, coloring
    from organlab.grid import VoxelGrid
    from organlab.session import load_session
    from organlab.silhouette import silhouettes

    session = load_session(a.session)
    cameras, source = session_cameras(session)
    images = [session.read(v.image, key=f"views[{i}].image") for i, v in enumerate(session.views)]
    t0 = time.perf_counter()
    masks = [s.mask for s in silhouettes(session)]
    t_sil = time.perf_counter() - t0
    grid = VoxelGrid.from_roi(session.roi_min, session.roi_max, a.voxel_size)
    t0 = time.perf_counter()
    hull = carving.carve(masks, cameras, grid)
    t_hull = time.perf_counter() - t0

    threads = os.environ.get("NUMBA_NUM_THREADS") or str(os.cpu_count())
    print(f"session   {session.root.name}: {len(images)} views, {session.image_size[0]} x {session.image_size[1]} px; cameras: {source}")
    print(f"grid      {grid.shape} at {grid.voxel_size:g} mm ({grid.n_voxels / 1e6:.2f} M voxels); numba threads {threads}")
    print(f"inputs    silhouettes {t_sil:.2f} s, hull (carve) {t_hull:.2f} s, {int(hull.sum())} hull voxels")

    hwm_before = vm_mb("VmHWM")
    res = coloring.color_voxels(images, cameras, hull, grid, masks=masks, method=a.method)  # warm-up
    times, cpu = [], []
    for _ in range(max(1, a.repeat)):
        t0, c0 = time.perf_counter(), time.process_time()
        res = coloring.color_voxels(images, cameras, hull, grid, masks=masks, method=a.method)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    hwm_after = vm_mb("VmHWM")

    ref = session.reference.get("volume_mm3")
    v_hull = grid.volume_of(hull)
    v_col = grid.volume_of(res.occupancy)
    print(
        f"coloring  {a.method}: best {min(times):.2f} s wall, median {np.median(times):.2f} s of {len(times)} runs; "
        f"CPU (all threads) {min(cpu):.2f} s; load average {os.getloadavg()[0]:.1f}"
    )
    print(f"memory    peak RSS {hwm_before:.0f} MB before colouring, {hwm_after:.0f} MB after (+{hwm_after - hwm_before:.0f} MB)")
    print(
        f"result    {res.n_candidates} candidates, {res.n_carved} carved ({res.n_carved_background} seen through "
        f"to the background), {res.n_visible} coloured, {res.n_hidden} hidden interior"
    )
    line = f"volumes   hull {v_hull / 1e3:.1f} cm^3, coloured {v_col / 1e3:.1f} cm^3"
    if ref:
        line += f", reference {ref / 1e3:.1f} cm^3 (hull {100 * (v_hull / ref - 1):+.2f} %, coloured {100 * (v_col / ref - 1):+.2f} %)"
    print(line)


if __name__ == "__main__":
    main()
