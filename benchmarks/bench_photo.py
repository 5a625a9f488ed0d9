"""Benchmark of the photo method (``--method photo``, issue 22) on scenes no default was tuned on.

Scenes (36 views, 640 x 480 px, known cameras, 1 mm voxels by default):

The hull is the one the engine's colouring starts from (the sub-voxel hull
field's occupancy; for the dino, the authors' masks' field at 0.5).

* ``bowls``, ``groove``: :class:`organlab.synthetic._textured.BowlSpecimen` and
  ``GrooveSaddleSpecimen`` under the hard lamp (rendered once into
  ``--cache``), scored against the exact shape: the hull's excess volume
  (hull outside the specimen, % of the true volume), the share of it the
  method removed, and the true volume lost (specimen outside the model);
  each voxel's inside fraction from 27 sub-samples;
* ``unseen``: a scene no constant was set on: ``BowlSpecimen(n_bowls=3,
  depth=7, seed=31)`` rendered with seed 9, scored the same way;
* ``aaa``: the bundled sample: the carved volume against the hull's, and
  scored against the exact phantom (``AAAPhantom``): its hull has excess
  too (a cone over the flat top cap, which no silhouette removes);
* ``dino``: the real dinoSparseRing photos with the authors' masks: the mean
  silhouette IoU of the carved model against the hull's.

For each ``--scale`` (times the default NCC gain) prints the figures, the
wall-clock and the CPU seconds (user + sys of the process during the call;
the machine may be shared, so CPU time is the steadier figure).  One warm-up
call at 4 mm first, so numba's compilation is not timed.

Usage::

    .venv/bin/python benchmarks/bench_photo.py bowls|groove|unseen|aaa|dino [--voxel-size 1] [--scale 0.5,1,2] [--cache /tmp/organlab_photo]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _cpu():
    t = os.times()
    return t.user + t.system


def _fraction_inside(spec, grid, region, n=3):
    idx = np.argwhere(region)
    off = ((np.arange(n) + 0.5) / n - 0.5) * grid.voxel_size
    o = np.stack(np.meshgrid(off, off, off, indexing="ij"), -1).reshape(-1, 3)
    out = np.zeros(grid.shape)
    for s in range(0, len(idx), 100_000):
        p = (np.asarray(grid.origin) + idx[s:s + 100_000] * grid.voxel_size)[:, None, :] + o[None]
        out[tuple(idx[s:s + 100_000].T)] = spec.inside(p.reshape(-1, 3)).reshape(-1, len(o)).mean(1)
    return out


def _scene(name, voxel_size, cache):
    import organlab as ol
    from organlab.synthetic import make_session
    from organlab.synthetic._textured import BowlSpecimen, GrooveSaddleSpecimen

    if name == "dino":
        from organlab.datasets import load_middlebury, middlebury_silhouettes

        data = load_middlebury(ROOT.parent / "shared" / "data" / "dinoSparseRing"
                               if not os.environ.get("ORGANLAB_SHARED_DATA")
                               else Path(os.environ["ORGANLAB_SHARED_DATA"]) / "dinoSparseRing")
        good = np.nonzero(data.good)[0]
        imgs = [data.images[i] for i in good]
        cams = [data.cameras[i] for i in good]
        masks = middlebury_silhouettes(imgs)
        grid = ol.VoxelGrid.from_roi(data.bbox[0] - 4.0, data.bbox[1] + 4.0, voxel_size)
        return None, imgs, cams, masks, grid
    if name == "aaa":
        from organlab.synthetic import with_true_cameras

        from organlab.synthetic._specimens import AAAPhantom

        folder = with_true_cameras(ROOT / "sample_sessions" / "aaa_phantom", Path(cache) / "aaa")
        spec = AAAPhantom()
    else:
        spec = {"bowls": BowlSpecimen, "groove": GrooveSaddleSpecimen,
                "unseen": lambda: BowlSpecimen(n_bowls=3, depth=7.0, seed=31)}[name]()
        folder = Path(cache) / name
        if not (folder / "session.json").is_file():
            make_session(folder, specimen=spec, n_views=36, hard=True, views_only=True, seed=9 if name == "unseen" else 5)
    s = ol.load_session(folder)
    cal, _ = ol.calibration_for(s)
    cams = cal.cameras(s)
    sils = ol.silhouettes(s)
    return spec, [s.read(v.image) for v in s.views], cams, sils, ol.VoxelGrid.from_session(s, voxel_size=voxel_size)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", choices=["bowls", "groove", "unseen", "aaa", "dino"])
    ap.add_argument("--voxel-size", type=float, default=1.0)
    ap.add_argument("--scale", default="0.5,1,2", help="multiples of the default NCC gain")
    ap.add_argument("--cache", default="/tmp/organlab_photo", help="where the rendered sessions are kept")
    a = ap.parse_args()

    from scipy import ndimage

    import organlab as ol
    from organlab.carving import hull_field
    from organlab.coloring import DEFAULT_PHOTO_THRESHOLD, photo_carve
    from organlab.raster import model_mask

    spec, imgs, cams, sils, grid = _scene(a.scene, a.voxel_size, a.cache)
    if a.scene == "dino":  # the authors' masks
        masks = sils
        hull = hull_field([m.astype(np.float32) for m in masks], cams, grid) >= 0.5
    else:  # the hull the engine colours: the sub-voxel hull field's occupancy
        masks = [x.mask for x in sils]
        hull = hull_field(sils, cams, grid, sparse=True).occupancy()
    coarse = ol.VoxelGrid.from_roi(*grid.bounds, 4.0)  # warm-up: numba compilation / cache loading
    photo_carve(imgs, cams, ol.carve(masks, cams, coarse), coarse, masks=masks, passes=1)
    frac = None if spec is None else _fraction_inside(spec, grid, ndimage.binary_dilation(hull, iterations=2))

    def figures(occ):
        out = {"volume_mm3": round(grid.volume_of(occ), 1)}
        if frac is not None:
            h3 = grid.voxel_size**3
            out["excess_pct"] = round(100 * (1 - frac)[occ].sum() * h3 / spec.volume, 3)
            out["lost_pct"] = round(100 * frac[~occ].sum() * h3 / spec.volume, 3)
        if a.scene == "dino":
            out["iou"] = round(float(np.mean([((r := model_mask(occ, c, grid=grid)) & m).sum() / (r | m).sum()
                                                for c, m in zip(cams, masks)])), 4)
        return out

    h = figures(hull)
    print(json.dumps({"scene": a.scene, "voxel_size": a.voxel_size, "views": len(cams), "hull": h}))
    for scale in (float(v) for v in a.scale.split(",")):
        t0, c0 = time.perf_counter(), _cpu()
        r = photo_carve(imgs, cams, hull, grid, masks=masks, threshold=scale * DEFAULT_PHOTO_THRESHOLD)
        wall, cpu = time.perf_counter() - t0, _cpu() - c0
        f = figures(r.occupancy)
        if "excess_pct" in f:
            f["excess_removed_pct"] = round(100 * (h["excess_pct"] - f["excess_pct"]) / h["excess_pct"], 1)
        f["volume_vs_hull_pct"] = round(100 * (f["volume_mm3"] / h["volume_mm3"] - 1), 3)
        print(json.dumps({"scale": scale, "threshold": r.threshold, **f, "restored_by_guard": r.n_restored,
                          "passes": r.iterations, "wall_s": round(wall, 1), "cpu_s": round(cpu, 1)}), flush=True)


if __name__ == "__main__":
    main()
