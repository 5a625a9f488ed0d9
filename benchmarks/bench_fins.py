"""Parts thinner than a voxel through :func:`organlab.surface.finish_surface` (issue 21): one row per analytic scene.

The scenes of tests/test_finish_fins.py at 1 mm: a 15 mm ball with three half-discs (``--thick`` voxels, seeds
``--seeds``), a cap and a tilted disc, as coverage fields and occupancies.  Per scene: the deviation from the raw
surface less its specks (max / mean, voxels), the smallest angle, closed and manifold, the volume change, faces, the
finishing's CPU time and the steps that ran.  Compare checkouts by running this with ``PYTHONPATH=other``.

    python benchmarks/bench_fins.py [--thick 0.4 0.5 0.6 0.7 0.8 0.9] [--seeds 0 1 2] [--kinds coverage occupancy]

Measured (helper `fins`, 2026-12-04, before -> after the thin parts' raw start, seeds 0-2): coverage 0.6-0.7
1.45-1.87 -> 0.44-0.68 voxel, 0.05-0.56 -> 20.9-21.9 deg; occupancy 0.4-0.9 all 18 within (7 were 2.0-3.2 voxels,
0.01-0.4 deg); coverage 0.4-0.5 still 1.31-2.17 voxels (a lace of islands and sub-voxel tunnels).  See
docs/surfaces.md.

Measured (helper `cfins`, 2026-12-04, the default scenes): before -> after samples exactly at the level were moved
below it (._bandmesh.untie) and parts thinner than 0.6 voxel thickened (._thin.thickened): coverage 0.4-0.5 seeds
0-2 0.80-2.21 -> 0.52-0.80 voxel, 18.7-21.6 -> 21.0-22.9 deg, no sliver cut or last step left; coverage 0.9 seed 0
(holes in the raw surface) 3.46 voxels, 8.3 deg -> 0.42, 21.5 deg; all 44 scenes within 0.33-0.80 voxel (mean
0.03-0.13), 21.1-28.7 deg, no last step (one sliver step: coverage 0.9 seed 1).  Occupancies as they were
(0.56-0.63 voxel).  Coverage fins seeds 3-11 (0.3-0.65 voxel thick, 39 scenes; seeds 9-11 rendered after the rule
was fixed): 0.38-0.93 voxel, 20.0-23.8 deg (before, on 27 of them: 0.48-8.94, 17 over a voxel).  Volume against the raw:
coverage fins +0.07 to +1.0 %, caps +0.65 / +1.04 %, discs +8.8 / +6.5 % (what thickening adds to the lace, whose
raw volume is under the true one: fins 0.4-0.5 voxel thick -4.1 to -4.4 %, the disc 0.5 voxel thick -25 %);
occupancies -0.53 to +0.34 % as before.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from organlab.surface import finish_surface, mesh_from_field, surface_deviation  # noqa: E402
from organlab.surface._repair import repair_mesh  # noqa: E402
from tests.test_finish_fins import capped_ball, disc_on_hub, finned_ball  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--thick", type=float, nargs="+", default=[0.4, 0.5, 0.6, 0.7, 0.8, 0.9])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--kinds", nargs="+", default=["coverage", "occupancy"])
    a = ap.parse_args(argv)
    scenes = {}
    for kind in a.kinds:
        for t in a.thick:
            for seed in a.seeds:
                scenes[f"fins {kind} {t:g} seed {seed}"] = lambda k=kind, t=t, s=seed: finned_ball(k, t, s)
        for t in (0.5, 0.7):
            scenes[f"cap {kind} {t:g}"] = lambda k=kind, t=t: capped_ball(k, t)
            scenes[f"disc {kind} {t:g}"] = lambda k=kind, t=t: disc_on_hub(k, t)
    print("| scene | max vox | mean vox | min angle deg | closed | volume % | faces | CPU s | steps |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, make in scenes.items():
        raw = mesh_from_field(*make())
        t0 = time.process_time()
        fin = finish_surface(raw, voxel_size=1.0)
        cpu = time.process_time() - t0
        dev = surface_deviation(fin.mesh, repair_mesh(raw, speck_mm=3.0)[0], voxel_size=1.0)
        steps = ", ".join(s["step"] for s in fin.steps if s["step"] not in ("repair", "smooth"))
        print(f"| {name} | {dev['max_voxels']:.3f} | {dev['mean_voxels']:.3f} | {fin.final['min_angle_deg']:.2f} | "
              f"{'yes' if fin.watertight else 'no'} | {fin.volume_change_pct:+.3f} | {len(fin.mesh.faces)} | {cpu:.2f} | "
              f"{steps} |", flush=True)


if __name__ == "__main__":
    main()
