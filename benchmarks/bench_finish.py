"""Finishing (:func:`organlab.surface.finish_surface`): time, peak memory, quality and how far it strays from the data.

For the sample (calibration given) at each voxel size, and for the shared dino photos when they are
present (``../shared/data/dinoSparseRing`` as a backdrop session with their published cameras, 1 mm):
the raw marching-cubes surface of the default run, then ``finish_surface`` on it with the run's pixel
footprint, CPU time (user + sys of this process, best of ``--repeat``; the machine is shared, so read
CPU time, and compare against another checkout's in alternating runs: ``PYTHONPATH=other python ...``),
the process's peak RSS, faces in and out, the smallest angle, the volume change, the deviation from
the raw surface (mean / max, voxels, both ways) and, for the dino, each view's IoU against the authors'
silhouettes, raw and finished (the worst change).

    python benchmarks/bench_finish.py [--voxel-sizes 1 0.5] [--repeat 3] [--no-dino] [--cache DIR]

``--cache DIR``: the sample's raw surfaces and footprints are read from ``DIR`` (written there by the first run
that lacks them), so that alternating runs of two checkouts finish the same surfaces without reconstructing
them; the per-view IoU is left out then (it needs the run's silhouettes).

Measured (issue 21/24, helper `finish`, a loaded 2-core machine, CPU best of 3; main at d745ade run
alternately in the same conditions): sample 1 mm 0.72 s against 1.40 s, 20 920 faces (19 160), 21.5
degrees (23.4), deviation mean 0.021 / max 0.31 voxel (0.032 / 0.67), worst view IoU -0.0009
(-0.0028), volume 0.000 % (+0.042 %); dino 1 mm 1.58 s against 3.58 s, 29 788 faces (16 866), 21.0
degrees (22.2), deviation 0.030 / 0.63 voxel (0.277 / 11.4), worst view +0.0011 (-0.0376);
0.25 mm sample 18.9 s CPU (main 38.3), peak 1246 MB in this process (main 1039), 143 160 faces, 21.3 degrees,
deviation 0.022 / 2.18 voxels (0.05 / 2.7).
Again on main of 2026-12-03 (helper `dino`, loaded, best of 3): sample 1 mm 0.90 s, dino 1 mm 1.80 s, every
other figure the same (the dino's session now from organlab.datasets.write_middlebury_session).
Issue 24 (helper `finish`, 2026-12-03, load 7-12 on 2 cores, warm, alternating with fcc61ee): sample
0.25 mm 17.9-19.3 s -> 12.5-14.9 s CPU (the sliver clean-up on regions around the bad faces, sweeps over
the faces left to do), the same 143 608 faces bit for bit; 1 mm 0.80-0.86 s both, 20 930 faces, 32.2 deg.
Issues 21/24 (helper `sliver`, 2026-12-03, load 13-23 on 2 cores, CPU best of 3 alternating with 8a93a8c, the
raw surfaces of this script cached): the last step (stay_on_data) made local -- sample 0.25 mm 39.4 -> 24.1 s
(the step 19.4 -> 3.4 s), the same 143 756 faces bit for bit, 21.06 deg, deviation 0.022 / 1.29 voxels (2.14
before the step: still over 1, a sheet 0.12-0.2 mm thick at (-13.6, 6.6, 61.7) mm); dino 1 mm with the joint
silhouettes (auto) 6.25 -> 5.34 s, the same 34 734 faces, 0.033 / 0.97 voxel, worst view IoU +0.0014; the
1 mm sample unchanged (the step does not run there).
Issue 21 (helper `sheets`, 2026-12-03, load 4-16 on 2 cores, CPU best of 3 alternating with e5194df; the raw
surfaces cached): the 1.29 voxels were a tunnel 0.5 mm across under a wall 0.08-0.2 mm thin, with a 0.1 mm pocket, at
(-13.6, 7.0, 61.8) mm, where four faces stayed below 20 degrees and the sliver cut of one target edge (0.69 mm, 2.8
voxels) filled over the tunnel (2.14 voxels off before stay_on_data).  Which figure a run gives depends on the raw
surface's last bits (OpenCV's threads: three reconstructions up to 6e-6 mm apart gave 0.88, 0.90 and 1.29 voxels).
The cut now takes the smallest radius that keeps the angle within a voxel (0.0875 mm, 33-36 faces), and repairs only
the pieces it touches.  0.25 mm sample: 0.60 / 0.69 / 0.69 voxel on those three (1.29 / 0.88 / 0.90), 21.27 degrees
(21.06 / 20.03 / 20.24), 143 980-144 084 faces, volume +0.000 %, stay_on_data not needed; finishing 15.7 s CPU
against 18.3 (the 1.29 one), 14.7 against 18.2 (the 0.88 one).  1 mm sample: the same mesh (20 934 faces, 30.4
degrees, 0.021 / 0.35 voxel), 0.71 against 0.73 s.  Dino 1 mm (joint auto): the cut's repair had dropped a separate
piece 57 mm away (3.1 voxels of raw surface lost): 34 102 faces (33 890), 20.8 degrees (20.1), -0.0006 % (-0.0055 %),
0.032 / 0.85 voxel (0.033 / 0.96), 2.76 s against 2.62 s CPU.
Issue 24 (helper `finspeed`, 2026-12-04 02:30-02:40 UTC, load 5-9 on 2 cores, CPU best of 3, alternating with dc59702,
``--cache``): the closest points from a numba uniform grid of the face centroids instead of scipy's k-d tree (the same
6 nearest centroids in the same order, so the same points, distances and faces; the grid's build 0.14 s against the
tree's 0.55 s on the 0.25 mm raw surface), ``Mesh.volume`` in blocks of faces (the same bits, 4.5x faster), the
remesher's collapse, flip and split kernels trimmed (their outputs the same on every captured call): the finished
meshes are the same bit for bit (1 mm: 20 934 faces, 30.4 degrees, 0.021 / 0.35 voxel; 0.25 mm: 143 982 faces, 21.3
degrees, 0.022 / 0.69 voxel).  Sample 1 mm 0.65 / 0.70 -> 0.41 / 0.40 s; 0.25 mm 11.8 / 10.3 -> 10.4 / 8.8 s (two
rounds each), peak RSS 715-727 -> 642-643 MB (this script with cached surfaces: the finishing's own peak).  Left at
0.25 mm (profile of the new code, 12.8 s CPU under load): the quality checks of each new mesh (``mesh_quality``, the
repair's defect checks: 2.8 s, a third of it the non-manifold-vertex fans), the collapses 2.0 s (a sweep revisits
every refused candidate), the closest-point queries 2.2 s (1.4 M points), flips 0.7 s, smoothing 0.7 s.
bench_viewer --sizes 1 --repeat 3 right after (loads 6-12, wall figures meaningless): finish_surface 0.407 s CPU of its
thread (dc59702 run next, at load 12: 0.565 s; the other stages 1.3-1.6x slower in that run), the full update 1.88 CPU
s of the process (2.63); no numba kernel compiled by the viewer.  The final code (9da7026, 03:00 UTC, load 7-11, two more
alternating rounds): 1 mm 0.61 / 0.71 -> 0.40 / 0.42 s, 0.25 mm 11.50 / 12.18 -> 9.15 / 9.62 s, peak 723-732 -> 649-654 MB.
Issue 24 (helper `fin025`, 2026-12-04 15:35-16:20 UTC, load 6-13 on 2 cores, alternating with 779e1a9, ``--cache``,
time.process_time per step of one run each, 4-5 rounds): the quality checks compiled (edge counts, pieces and
referenced vertices in one pass over the edge table; a closed surface's vertex fans walked once instead of
log2(valence) pointer-doubling passes; an open one's by union-find; the repair's duplicate-vertex check by hashing,
its defects once per mesh, its specks by union-find), and the remesher's collapse and flip sweeps visit a face
refused for its neighbourhood's shape again only when a face at one of its corners changed.  The same meshes bit
for bit (sha1 of vertices, faces and report).  0.25 mm: finishing 11.2-14.6 -> 9.8-11.2 s; mesh_quality 2.5-3.0
-> 1.5-2.0 s (9 checks; about 0.4 s of it is the process's first numba call, 0.45 s the edge sorts of the raw
surface), repair 3.2-3.9 -> 1.9-2.3 s, the collapse kernel 1.5 -> 1.1 s and the flips 0.7 -> 0.5 s (sums over
the run), adaptive_remesh 4.1-5.8 -> 4.0-4.5 s; 1 mm 0.47-0.50 -> 0.44-0.52 s (no change to read).  Left at
0.25 mm: the closest-point queries (relaxations, deviation, stay_on_data: about 4 s), the first collapse sweeps
on the 0.93 M raw faces (8 x 0.06-0.09 s), the raw surface's two edge sorts (organlab/mesh.py).
The whole default ``organlab reconstruct`` of the true-camera sample (``with_true_cameras``), /usr/bin/time user +
sys, 7 alternating pairs with 779e1a9 (16:00-16:32 UTC, load 3-13): 0.25 mm 20.5-26.5 s (median 23.7) -> 19.4-23.6 s
(median 21.9), 1.0-4.3 s less in every pair (mean 2.8 s), peak RSS 948-961 -> 842-852 MB (the corner graphs
of scipy's components gone), the same mesh.ply and mesh.stl bytes; 1 mm 3.95-4.19 s both (3 pairs), same files.
Issue 24 (helper `fin1`, 2026-12-04 18:30-19:10 UTC, load 1.4-5 on 2 cores, ``--cache``, alternating with 77e2ecf):
the closest-point queries in chunks of 2 048 points taken in turn by daemon helper threads (the deviation's two
directions in one call), the Taubin steps and vertex normal sums compiled, a moved mesh's face figures computed only
when asked; the same meshes and reports (sha1) on the sample 1 mm (the viewer's and this script's raw surfaces),
0.25 mm, the dino 1 mm and an occupancy.  1 mm: 0.44/0.46/0.49 -> 0.45/0.43/0.46 s CPU (3 rounds, best of 5; the
pieces: Taubin loop 23 -> 15 ms, normal sums 14 -> 2 ms, two face-figure passes on the raw surface fewer); 0.25 mm:
peak RSS 564/565 -> 539/540 MB, CPU 16.1/11.6 -> 10.7/12.2 s.  Left at 1 mm (profile, 0.45-0.6 s CPU): the
remesher (adaptive_remesh + fit_faces, 0.39 s; its closest-point queries 0.22 s of the whole, about 1 us a point),
the deviation (60 k points, 0.06 s), smoothing 0.03 s, the raw surface's quality 0.02 s.
Issue 24 (helper `rem1`, 2026-12-04 19:15-19:50 UTC, load 1-3 on 2 cores, ``--cache``, alternating with b64c22b): the
remesher's numpy glue compiled with the numpy operations in the same order (the relaxation's choice per vertex, in
place; fit_faces' gaps and centroids; _compact; numpy 2.4's einsum sums three products as ``(p0 + p2) + p1``), and the
grid's k-nearest search skipping whole slabs of cells (the same cells in the same order).  The same meshes (sha1 of
vertices and faces) on the sample 1 mm and 0.25 mm, the dino 1 mm and two fin scenes.  1 mm, CPU best of 5, 3 rounds
in each of two sets: 0.58/0.58/0.52 -> 0.51/0.51/0.47 s and 0.62/0.64/0.65 -> 0.56/0.57/0.57 s.  Pieces (perf_counter,
best of 5 runs): the relaxations' numpy after their queries 25 -> 3 ms, fit_faces 51 -> 19 ms (its query 25 ms of the
first), _compact 10 -> 3.5 ms; the closest-point kernel (about 1.2 us a point, 121 k points a finishing, 0.1-0.15 s)
unchanged within the noise.  0.25 mm: 10.2-14.2 s CPU both (noise), peak 534-541 MB (539-540).  Left at 1 mm: the
closest points (96 ms of the remesher's 225), the collapse sweeps 64 ms, flips 25 ms; warm-starting the relaxations'
queries would need each vertex's candidates carried through the splits and collapses, not tried.
Issue 24 (helper `remw`, 2026-12-04 21:40-22:10 UTC, load 3-8 on 2 cores, ``--cache``, alternating with 672b505): the
face normal and centroid kernels moved to surface/_geom (shared by _deviation and _remesh), the same meshes (sha1)
on the sample 1 mm and 0.25 mm (two raw surfaces each), the dino 1 mm, coverage fins 0.4 s0, occupancy 0.6 s1;
1 mm 0.47/0.42/0.38 -> 0.38/0.39/0.35 s CPU (best of 5, 3 rounds: the noise), 0.25 mm 9.99/10.00/10.25 ->
9.59/9.74/9.96 s, peak 534-567 -> 537-541 MB.  Where the 1 mm finishing goes (0.41-0.46 s CPU, process_time per
step, median of 5): the closest-point queries 175 ms (11 a run, 181 k points, 0.7-1.2 us a point: staircase 5 773,
the remesher's start 28 864, six relaxations 10 469-12 786 at k = 4, fit_faces 20 934, the deviation 31 403 +
28 864), collapse sweeps 55, mesh_quality 40, smoothing 30, repair 25, flips 25, _retest 14, volume 12, splits 10.
A warm start of the queries cannot pay: given each point's exact k-th centroid distance in advance (the best
bound a previous face could give), the relaxations' search reads 31.1 centroids a point instead of 34.5 and 7.6
cells instead of 8.5, 0-7 % of the search (5.4-5.9 -> 5.2-5.5 ms a query; the search is 70 % of the kernel); grid
cells of 1, 1.5 and 3 mean edges are all slower than 2 (the same results), inlining the search 3 %.  In the
command, finish_surface runs once, and its first call loads 21 numba kernels from the cache (0.12 s CPU; the
first call 0.57-0.61 s against 0.38-0.44 s for the next ones, after other kernels loaded numba's registries); a
tiny finish_surface beforehand (a 13^3 ball, 0.17-0.22 s CPU, e.g. on the command's loading thread) brings the
first call to 0.50 s.
The repeats now finish a new Mesh each time (before, the second and third reused the raw surface's cached edge
table and quality figures: about 0.5 s less at 0.25 mm than a real run).
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from organlab.engine import pixel_footprint
from organlab.mesh import Mesh
from organlab.pipeline import reconstruct
from organlab.raster import model_mask
from organlab.surface import finish_surface

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_sessions" / "aaa_phantom"
DINO = Path(os.environ.get("ORGANLAB_SHARED_DATA", ROOT.parent / "shared" / "data")) / "dinoSparseRing"


def _cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _peak_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _finish(raw, vs, foot, repeat):
    best = np.inf
    for _ in range(repeat):
        # a new Mesh each time: a mesh caches its edge table and quality figures, which a second run on the same
        # object would not compute (0.25 mm: about 0.5 s CPU left out of the repeats before 2026-12-04)
        fresh = Mesh(raw.vertices.copy(), raw.faces.copy())
        t = _cpu()
        fin = finish_surface(fresh, voxel_size=vs, min_edge_mm=foot)
        best = min(best, _cpu() - t)
    return fin, best


def _row(name, vs, raw, fin, cpu, extra=""):
    d = fin.deviation
    print(f"| {name} | {vs:g} | {cpu:.2f} | {_peak_mb():.0f} | {len(raw.faces)} | {len(fin.mesh.faces)} | "
          f"{fin.final['min_angle_deg']:.1f} | {fin.volume_change_pct:+.3f} | {d['mean_voxels']:.3f} | "
          f"{d['max_voxels']:.2f} | {extra} |", flush=True)


def _ious(mesh, cams, masks):
    return np.array([((r := model_mask(mesh, c, m.shape)) & m).sum() / (r | m).sum() for c, m in zip(cams, masks)])


def _dino_session(tmp):
    from organlab.datasets import load_middlebury, middlebury_silhouettes, write_middlebury_session

    data = load_middlebury(DINO)
    good = write_middlebury_session(data, DINO, tmp)
    return [data.cameras[i] for i in good], middlebury_silhouettes([data.images[i] for i in good])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--voxel-sizes", type=float, nargs="+", default=[1.0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-dino", action="store_true")
    ap.add_argument("--cache", type=Path, default=None, help="directory of cached raw surfaces of the sample")
    a = ap.parse_args(argv)
    print("| scene | voxel mm | finish CPU s | peak RSS MB | faces in | faces out | min angle deg | volume % | "
          "deviation mean vox | max vox | IoU per view |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for vs in a.voxel_sizes:
        cached = a.cache / f"sample_raw_{vs:g}mm.npz" if a.cache is not None else None
        if cached is not None and cached.is_file():
            with np.load(cached) as z:
                raw, foot = Mesh(z["vertices"], z["faces"]), float(z["footprint"])
            fin, cpu = _finish(raw, vs, foot, a.repeat)
            _row("sample", vs, raw, fin, cpu, "(cached raw surface)")
            continue
        rec = reconstruct(SAMPLE, voxel_size=vs, finish=False)
        if cached is not None:
            cached.parent.mkdir(parents=True, exist_ok=True)
            np.savez(cached, vertices=rec.raw_mesh.vertices, faces=rec.raw_mesh.faces,
                     footprint=pixel_footprint(rec.cameras, rec.grid))
        fin, cpu = _finish(rec.raw_mesh, vs, pixel_footprint(rec.cameras, rec.grid), a.repeat)
        extra = ""
        if vs >= 1.0:  # each view's IoU with the model's own silhouettes, raw and finished (as report.json's)
            sils = [np.asarray(s.coverage) >= 0.5 for s in rec.silhouettes]
            ir, ifin = _ious(rec.raw_mesh, rec.cameras, sils), _ious(fin.mesh, rec.cameras, sils)
            k = int(np.argmax(np.abs(ifin - ir)))
            extra = f"(own silhouettes) raw {ir.mean():.4f}, finished {ifin.mean():.4f}, worst view {k} {ifin[k] - ir[k]:+.4f}"
        _row("sample", vs, rec.raw_mesh, fin, cpu, extra)
    if not a.no_dino and (DINO / "dinoSR_par.txt").is_file():
        with tempfile.TemporaryDirectory() as tmp:
            cams, masks = _dino_session(Path(tmp) / "dino")
            rec = reconstruct(Path(tmp) / "dino", voxel_size=1.0, finish=False)
            fin, cpu = _finish(rec.raw_mesh, 1.0, pixel_footprint(rec.cameras, rec.grid), a.repeat)

            ir, ifin = _ious(rec.raw_mesh, cams, masks), _ious(fin.mesh, cams, masks)
            k = int(np.argmax(np.abs(ifin - ir)))
            _row("dino", 1.0, rec.raw_mesh, fin, cpu,
                 f"(authors' masks) raw {ir.mean():.4f}, finished {ifin.mean():.4f}, worst view {k} {ifin[k] - ir[k]:+.4f}")
    elif not a.no_dino:
        print(f"(dino skipped: {DINO} not found)", file=sys.stderr)


if __name__ == "__main__":
    main()
