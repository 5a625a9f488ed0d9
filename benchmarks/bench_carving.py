"""Benchmark of visual-hull carving: plain numpy vs organlab vs Open3D.

Same masks and cameras for every method: 36 views (every 10 degrees of the
turntable), 640 x 480 px, the synthetic sessions' camera (strong barrel
distortion), silhouettes of an AAA-like phantom (``organlab.synthetic``'s
``render_masks`` when it exists, else a union of cylinders and spheres ray
cast here through ``Camera.rays``).  Grids: 80 x 80 x 180 voxels at 1 mm
(1.15 M voxels) and 160 x 160 x 360 at 0.5 mm (9.2 M voxels).

Each method runs in its own subprocess (so its peak memory, VmHWM, is its
own, including the interpreter, numpy and the loaded masks); times are wall-clock seconds of the carving call alone, best of
``--repeat`` runs after one warm-up run (numba compilation excluded).

Usage::

    .venv/bin/python benchmarks/bench_carving.py [--repeat 3] [--skip-reference-fine]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np
from _common import vm_mb  # benchmarks/_common.py (scripts run from this folder)

N_VIEWS = 36
GRIDS = {"1mm": 1.0, "0.5mm": 0.5}
ROI_MIN = (-40.0, -40.0, 0.0)
ROI_MAX = (40.0, 40.0, 180.0)


# ------------------------------------------------------------------ scene
def _camera():
    try:
        from organlab.synthetic import default_camera

        return default_camera((640, 480))
    except ImportError:  # pragma: no cover - synthetic not available
        from organlab.camera import Camera

        az = np.deg2rad(-82.0)
        c = np.array([505.0 * np.cos(az), 505.0 * np.sin(az), 350.0])
        z = np.array([0.0, 0.0, 88.0]) - c
        z /= np.linalg.norm(z)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        K = [[812.4, 0, 324.7], [0, 809.7, 236.1], [0, 0, 1]]
        return Camera(K, [-0.3, 0.1, 1.2e-3, -0.8e-3, 0.0], R, -R @ c, (640, 480))


# union of spheres (centre, radius) and vertical cylinders (x, y, r, z0, z1), mm
SPHERES = [((0.0, 0.0, 95.0), 27.0), ((6.0, 4.0, 75.0), 20.0)]
CYLINDERS = [(0.0, 0.0, 11.0, 20.0, 172.0), (-9.0, 2.0, 6.5, 2.0, 45.0), (9.0, -2.0, 6.5, 2.0, 45.0)]


def _hits(o, d):
    """Whether rays (o, d) hit the phantom."""
    hit = np.zeros(len(d), dtype=bool)
    for c, r in SPHERES:
        oc = o - np.asarray(c)
        b = np.einsum("ij,ij->i", oc, d)
        disc = b * b - (np.einsum("ij,ij->i", oc, oc) - r * r)
        hit |= (disc >= 0) & (-b + np.sqrt(np.maximum(disc, 0)) > 0)
    for x, y, r, z0, z1 in CYLINDERS:
        ox, oy = o[:, 0] - x, o[:, 1] - y
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = ox * d[:, 0] + oy * d[:, 1]
        disc = b * b - a * (ox * ox + oy * oy - r * r)
        ok = disc >= 0
        sq = np.sqrt(np.maximum(disc, 0))
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = (-b - sq) / a
            t1 = (-b + sq) / a
            # z slab
            tz0 = (z0 - o[:, 2]) / d[:, 2]
            tz1 = (z1 - o[:, 2]) / d[:, 2]
        lo = np.maximum(t0, np.minimum(tz0, tz1))
        hi = np.minimum(t1, np.maximum(tz0, tz1))
        hit |= ok & (lo <= hi) & (hi > 0)
    return hit


def make_scene():
    """36 cameras and silhouettes (bool (480, 640)) of the phantom."""
    cam0 = _camera()
    angles = np.arange(N_VIEWS) * (360.0 / N_VIEWS)
    cameras = [cam0.at_table_angle(a) for a in angles]
    try:
        from organlab.synthetic import AAAPhantom, render_masks

        return cameras, list(render_masks(AAAPhantom(), cameras)), "organlab.synthetic.render_masks(AAAPhantom())"
    except (ImportError, TypeError, AttributeError):
        pass
    w, h = cam0.image_size
    uu, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    pix = np.stack([uu.ravel(), vv.ravel()], axis=1)
    _, d0 = cameras[0].rays(pix)  # same intrinsics: rotate the directions per view
    d_cam = d0 @ cameras[0].R.T
    masks = []
    for cam in cameras:
        d = d_cam @ cam.R
        o = np.broadcast_to(cam.center, d.shape)
        masks.append(_hits(o, d).reshape(h, w))
    return cameras, masks, "union of 2 spheres and 3 cylinders ray cast in bench_carving.py"


def make_grid(voxel_size):
    from organlab.grid import VoxelGrid

    return VoxelGrid.from_roi(ROI_MIN, ROI_MAX, voxel_size)


# ---------------------------------------------------------------- methods
def run_reference(masks, cameras, grid):
    from organlab.carving._bbox import carve_reference

    return carve_reference(masks, cameras, grid)


def run_organlab(masks, cameras, grid):
    from organlab.carving._bbox import carve

    return carve(masks, cameras, grid)


def run_open3d(masks, cameras, grid):
    """Open3D's VoxelGrid.carve_silhouette on the same grid (pinhole only:
    Open3D's camera has no distortion, so its hull differs slightly)."""
    import open3d as o3d

    lo, hi = grid.bounds
    vg = o3d.geometry.VoxelGrid.create_dense(
        origin=lo, color=[0.5, 0.5, 0.5], voxel_size=grid.voxel_size,
        width=float(hi[0] - lo[0]), height=float(hi[1] - lo[1]), depth=float(hi[2] - lo[2]),
    )
    for m, cam in zip(masks, cameras):
        ext = np.eye(4)
        ext[:3, :3] = cam.R
        ext[:3, 3] = cam.t
        params = o3d.camera.PinholeCameraParameters()
        params.intrinsic = o3d.camera.PinholeCameraIntrinsic(
            cam.width, cam.height, cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
        )
        params.extrinsic = ext
        img = o3d.geometry.Image(m.astype(np.float32))
        vg.carve_silhouette(img, params, keep_voxels_outside_image=True)
    occ = np.zeros(grid.shape, dtype=bool)
    idx = np.array([v.grid_index for v in vg.get_voxels()], dtype=int).reshape(-1, 3)
    idx = idx[np.all((idx >= 0) & (idx < np.array(grid.shape)), axis=1)]
    occ[tuple(idx.T)] = True
    return occ


METHODS = {"numpy reference": run_reference, "organlab carve": run_organlab, "open3d carve_silhouette": run_open3d}


def _peak_rss_mb():
    """Peak resident memory of this process, MB (VmHWM: this program only;
    ru_maxrss would include the parent's memory from before the exec)."""
    peak = vm_mb("VmHWM")
    return peak if peak == peak else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _child(method, voxel_size, scene_file, repeat, out_file):
    data = np.load(scene_file)
    from organlab.camera import Camera

    cams = json.loads(str(data["cameras"]))
    cameras = [Camera.from_dict(c) for c in cams]
    masks = list(data["masks"])
    grid = make_grid(voxel_size)
    fn = METHODS[method]
    times = []
    cpu = []
    occ = None
    n_runs = repeat + (1 if method == "organlab carve" else 0)  # warm-up: numba compile
    for i in range(n_runs):
        t = time.perf_counter()
        c = time.process_time()
        occ = fn(masks, cameras, grid)
        dt = time.perf_counter() - t
        dc = time.process_time() - c
        if method == "organlab carve" and i == 0:
            continue
        times.append(dt)
        cpu.append(dc)
    rss_mb = _peak_rss_mb()
    np.save(out_file + ".npy", occ)
    with open(out_file, "w") as f:
        json.dump({"time_s": min(times), "times_s": times, "cpu_s": min(cpu), "peak_rss_mb": rss_mb, "n_kept": int(occ.sum())}, f)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3, help="timed runs per method (best is reported)")
    ap.add_argument("--skip-reference-fine", action="store_true", help="skip the slow numpy run at 0.5 mm")
    ap.add_argument("--child", nargs=5, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        method, vs, scene, repeat, out = args.child
        _child(method, float(vs), scene, int(repeat), out)
        return
    try:
        import open3d  # noqa: F401

        have_o3d = True
    except ImportError:
        have_o3d = False
    t = time.perf_counter()
    cameras, masks, source = make_scene()
    print(f"load average before: {os.getloadavg()[0]:.2f}")
    print(f"scene: {N_VIEWS} views {cameras[0].image_size[0]}x{cameras[0].image_size[1]}, {source} "
          f"({time.perf_counter() - t:.1f} s to render); cores: {os.cpu_count()}")
    tmp = tempfile.mkdtemp(prefix="bench_carving_")
    scene_file = os.path.join(tmp, "scene.npz")
    np.savez(scene_file, masks=np.array(masks), cameras=json.dumps([c.to_dict() for c in cameras]))
    results = {}
    for label, vs in GRIDS.items():
        grid = make_grid(vs)
        print(f"\ngrid {label}: {grid.shape} = {grid.n_voxels / 1e6:.2f} M voxels")
        for method in METHODS:
            if method.startswith("open3d") and not have_o3d:
                print(f"  {method:26s} skipped (open3d not installed)")
                continue
            repeat = args.repeat
            if method == "numpy reference":
                if label == "0.5mm" and args.skip_reference_fine:
                    print(f"  {method:26s} skipped (--skip-reference-fine)")
                    continue
                repeat = 1
            if method.startswith("open3d"):
                repeat = 1
            out = os.path.join(tmp, f"{label}_{method.split()[0]}.json")
            cmd = [sys.executable, __file__, "--child", method, str(vs), scene_file, str(repeat), out]
            subprocess.run(cmd, check=True)
            with open(out) as f:
                r = json.load(f)
            r["occ"] = np.load(out + ".npy")
            results[(label, method)] = r
            r["load"] = os.getloadavg()[0]
            print(f"  {method:26s} {r['time_s']:8.3f} s wall  {r['cpu_s']:8.3f} s CPU   peak RSS {r['peak_rss_mb']:7.0f} MB   "
                  f"kept {r['n_kept']} voxels  (load avg {r['load']:.1f})")
        ref = results.get((label, "numpy reference"))
        fast = results.get((label, "organlab carve"))
        o3d_r = results.get((label, "open3d carve_silhouette"))
        if ref and fast:
            diff = int(np.count_nonzero(ref["occ"] != fast["occ"]))
            print(f"  organlab vs numpy: {ref['time_s'] / fast['time_s']:.1f}x faster wall, "
                  f"{ref['cpu_s'] / fast['cpu_s']:.1f}x less CPU, "
                  f"{diff} voxels differ (must be 0)")
        if o3d_r and fast:
            diff = int(np.count_nonzero(o3d_r["occ"] != fast["occ"]))
            print(f"  organlab vs open3d: {o3d_r['time_s'] / fast['time_s']:.1f}x faster wall, "
                  f"{o3d_r['cpu_s'] / fast['cpu_s']:.1f}x less CPU "
                  f"({diff} voxels differ: open3d has no lens distortion and tests voxel centres)")


if __name__ == "__main__":
    main()
