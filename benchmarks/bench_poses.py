"""Pose refinement (issue 20): its time on 36 views of 640 x 480, and what it corrects.

Renders (once, into ``--cache``) sessions of an AAA of the sample's family with
another shape (``aaa-7``) and of the non-AAA ``dented`` specimen, 36 views of
640 x 480 px, intrinsics given, turntable calibrated from 8 board images:

* ``ok_aaa7``: nothing went wrong;
* ``drift_aaa7`` / ``drift_dented``: the table lost steps, the true angles drift
  linearly to +3 degrees over the turn plus 0.3 degrees of jitter per stop;
* ``bump_aaa7``: the camera bumped after the board images (0.7 degrees, 1.4 mm);
* ``slip_aaa7``: the specimen slid (1.2, -0.9) mm on the plate from view 18 on.

For each: the time of :func:`organlab.poses.refine_poses` (best of
``--repeat``, silhouettes and calibration excluded), its decision, the
per-view angle error (median / max) and the camera-centre error before and
after, against ``truth.json``.  With ``--voxel-size`` the whole pipeline also
runs with ``--refine-poses off`` and ``on`` and prints the mesh volume error
against the specimen's exact volume.

Usage::

    .venv/bin/python benchmarks/bench_poses.py [--cache /tmp/organlab_bench_poses] [--scenes bump_aaa7 ...]
        [--repeat 3] [--voxel-size 1]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def drift_angles(n, seed, total=3.0, jitter=0.3):
    g = np.random.default_rng(seed)
    return 360.0 * np.arange(n) / n + total * np.arange(n) / (n - 1) + np.concatenate([[0.0], g.normal(0, jitter, n - 1)])


def scenes(n=36, size=(640, 480)):
    base = dict(image_size=size, n_views=n, n_intrinsic=0, n_turntable=8, n_background=5, supersample=2, board_supersample=3,
                noise_sigma=1.0, include_camera=True, include_poses=False)
    return {
        "ok_aaa7": dict(base, seed=1, specimen="aaa-7"),
        "drift_aaa7": dict(base, seed=2, specimen="aaa-7", true_angles_deg=drift_angles(n, 5)),
        "bump_aaa7": dict(base, seed=3, specimen="aaa-7", camera_bump={"rotation_deg": (0.3, 0.6, 0.2), "translation_mm": (1.2, -0.6, 0.4)}),
        "slip_aaa7": dict(base, seed=4, specimen="aaa-7", slip={"view": n // 2, "translation_mm": (1.2, -0.9), "rotation_deg": 0.0}),
        "drift_dented": dict(base, seed=6, specimen="dented", true_angles_deg=drift_angles(n, 8)),
    }


def main(argv=None):
    from organlab.calibration import calibration_for
    from organlab.poses import refine_poses
    from organlab.session import load_session
    from organlab.silhouette import silhouettes
    from organlab.synthetic import make_session

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/organlab_bench_poses"))
    ap.add_argument("--scenes", nargs="+", default=list(scenes()))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--voxel-size", type=float, default=None)
    a = ap.parse_args(argv)
    for name in a.scenes:
        folder = a.cache / f"{name}_36"
        if not (folder / "truth.json").is_file():
            t0 = time.perf_counter()
            make_session(folder, **scenes()[name])
            print(f"rendered {folder} in {time.perf_counter() - t0:.0f} s")
        s = load_session(folder)
        truth = json.loads((folder / "truth.json").read_text())
        cal, _ = calibration_for(s)
        sils = silhouettes(s)
        times = []
        for _ in range(max(1, a.repeat)):
            t0, c0 = time.perf_counter(), time.process_time()
            r = refine_poses(s, cal, sils, mode="on")
            times.append((time.perf_counter() - t0, time.process_time() - c0))
        wall, cpu = min(times)
        cmd = np.array([v.angle_deg for v in s.views])
        true = np.array([v.get("true_angle_deg", v["angle_deg"]) for v in truth["views"]])
        e0 = np.abs(cmd - true)
        e1 = np.abs(cmd + (r.angle_corrections_deg if r.accepted else 0.0) - true)
        Rt, tt = np.array(truth["views"][0]["R"]), np.array(truth["views"][0]["t"])
        ct = -Rt.T @ tt
        c0 = np.linalg.norm(cal.cameras(s)[0].center - ct)
        c1 = np.linalg.norm(r.cameras[0].center - ct)
        print(f"{name}: {wall:.2f} s wall, {cpu:.2f} s CPU; largest view residual before {np.nanmax(r.before_px):.3f} px; {r.reason}")
        print(f"  angle error median/max {np.median(e0):.3f}/{e0.max():.3f} -> {np.median(e1):.3f}/{e1.max():.3f} deg; "
              f"camera centre error {c0:.2f} -> {c1:.2f} mm; slip {r.slip}; candidates {r.gate.get('candidates')}")
        if a.voxel_size:
            from organlab.pipeline import reconstruct

            for mode in ("off", "on"):
                t0 = time.perf_counter()
                rep = reconstruct(s, voxel_size=a.voxel_size, refine_poses=mode).report
                print(f"  {a.voxel_size:g} mm, --refine-poses {mode}: mesh volume {rep['mesh_volume_error_pct']:+.2f} % "
                      f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
