"""Pose refinement (issue 20): its time on 36 views of 640 x 480, and what it corrects.

Renders (once, into ``--cache``) sessions of an AAA of the sample's family with
another shape (``aaa-7``) and of the non-AAA ``dented`` specimen, 36 views of
640 x 480 px, intrinsics given, turntable calibrated from 8 board images:

* ``ok_aaa7``: nothing went wrong;
* ``drift_aaa7`` / ``drift_dented``: the table lost steps, the true angles drift
  linearly to +3 degrees over the turn plus 0.3 degrees of jitter per stop;
* ``driftb_dented``: the same with another render (seed) and another drift;
* ``drift_aaa11`` / ``ok_aaa11``: another drift (seed 25) on ``aaa-11`` (its outline shows its angles, its
  hull is near its volume), and the same render with the true angles;
* ``drift_br11`` / ``ok_br11``: another drift (seed 35) on ``aaa-11+branch`` (``aaa-11`` with two renal-artery-like
  stumps near its top, :class:`organlab.synthetic.BranchedAAA`: its outline shows its angles, its hull is near its
  volume), and the same render with the true angles; ``driftb_br11``: another render and drift (seed 45), no
  default chosen on it; ``driftc_br11``: a third (seeds 61 / 65), rendered after the angles' prior was chosen;
  ``driftd_br11``: a fourth (seeds 71 / 75), rendered after the view-by-view scan was added;
  ``drifte_br13`` / ``driftf_br3``: the same drift on ``aaa-13+branch`` / ``aaa-3+branch`` (seeds 81 / 85, 91 / 95);
  ``drifth_br11``: a drift on ``aaa-11+branch`` under the hard lamp (``hard=True``: cast shadows at the specimen's
  foot, highlights, exposure, JPEG; seeds 101 / 105);
* ``bump_aaa7``: the camera bumped after the board images (0.7 degrees, 1.4 mm);
* ``bumpb_aaa11``: another bump (0.71 degrees, 1.92 mm, other directions) on another AAA (``aaa-11``);
* ``slip_aaa7``: the specimen slid (1.2, -0.9) mm on the plate from view 18 on;
* ``drift_dented+audit`` / ``drift_aaa7+audit``: the drifting tables with the capture's angle
  audit (emulated: each stop's true angle plus the audit's error, sd 0.03 degrees; docs/capture.md
  measured it below 0.01 degrees at 640 x 480) in ``session.json`` ``capture.audit``, the prior;
* ``sample``: the bundled sample (``sample_sessions/aaa_phantom``, correct), decision and volume only.

For each: the time of :func:`organlab.poses.refine_poses` (best of
``--repeat``, wall and CPU, silhouettes and calibration excluded), its decision, the
per-view angle error of the cameras it returns (median / max) and the camera-centre error before and
after, against ``truth.json`` (also modulo a turn about the table axis: the specimen's orientation
on the plate, which no silhouette shows).  With ``--voxel-size`` the whole pipeline also
runs with ``--refine-poses off`` and ``on`` and prints the mesh volume error
against the specimen's exact volume.

Usage::

    .venv/bin/python benchmarks/bench_poses.py [--cache /tmp/organlab_bench_poses] [--scenes bump_aaa7 ...]
        [--repeat 3] [--voxel-size 1] [--supersample 2]

``--supersample N`` renders the views and background frames with N x N sub-pixel samples per pixel (box
filter; 2 by default, the renders above; the board images stay at 3) into ``<scene>_36_ssN`` (``<scene>_36``
for 2): the same seeds, drifts and noise, pixels that integrate more like a sensor's.
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


def scenes(n=36, size=(640, 480), supersample=2):
    base = dict(image_size=size, n_views=n, n_intrinsic=0, n_turntable=8, n_background=5, supersample=supersample, board_supersample=3,
                noise_sigma=1.0, include_camera=True, include_poses=False)
    return {
        "ok_aaa7": dict(base, seed=1, specimen="aaa-7"),
        "drift_aaa7": dict(base, seed=2, specimen="aaa-7", true_angles_deg=drift_angles(n, 5)),
        "bump_aaa7": dict(base, seed=3, specimen="aaa-7", camera_bump={"rotation_deg": (0.3, 0.6, 0.2), "translation_mm": (1.2, -0.6, 0.4)}),
        # another bump (other direction, another render and AAA), for the plate's rim chosen on the one above
        "bumpb_aaa11": dict(base, seed=13, specimen="aaa-11",
                            camera_bump={"rotation_deg": (-0.4, -0.5, 0.3), "translation_mm": (-0.8, 1.5, -0.9)}),
        "slip_aaa7": dict(base, seed=4, specimen="aaa-7", slip={"view": n // 2, "translation_mm": (1.2, -0.9), "rotation_deg": 0.0}),
        "drift_dented": dict(base, seed=6, specimen="dented", true_angles_deg=drift_angles(n, 8)),
        # another render and another drift, for the defaults chosen on the one above
        "driftb_dented": dict(base, seed=16, specimen="dented", true_angles_deg=drift_angles(n, 18)),
        # a drift on a specimen whose outline shows its angles (aaa-11: not rotation-symmetric) and whose hull is
        # near its volume (no hidden concavity, unlike dented); another render and drift; and its correct twin
        "drift_aaa11": dict(base, seed=21, specimen="aaa-11", true_angles_deg=drift_angles(n, 25)),
        "ok_aaa11": dict(base, seed=21, specimen="aaa-11"),
        # aaa-11 with two renal-artery-like stumps near its top (BranchedAAA): its outline shows its angles and
        # its hull is near its volume; a drift to look at, another render and drift no default was chosen on,
        # and the first one's correct twin
        "drift_br11": dict(base, seed=31, specimen="aaa-11+branch", true_angles_deg=drift_angles(n, 35)),
        "driftb_br11": dict(base, seed=41, specimen="aaa-11+branch", true_angles_deg=drift_angles(n, 45)),
        "ok_br11": dict(base, seed=31, specimen="aaa-11+branch"),
        # a third render and drift, rendered after the trend + jitter prior was chosen (nothing chosen on it)
        "driftc_br11": dict(base, seed=61, specimen="aaa-11+branch", true_angles_deg=drift_angles(n, 65)),
        # and a fourth, rendered after the view-by-view scan (_refine._polish) was added on seeing driftc_br11
        "driftd_br11": dict(base, seed=71, specimen="aaa-11+branch", true_angles_deg=drift_angles(n, 75)),
        # two more, on other branched AAAs, rendered to check the angles' sd and the maximum (session 7, nothing chosen on them)
        "drifte_br13": dict(base, seed=81, specimen="aaa-13+branch", true_angles_deg=drift_angles(n, 85)),
        "driftf_br3": dict(base, seed=91, specimen="aaa-3+branch", true_angles_deg=drift_angles(n, 95)),
        # the drift under a hard lamp (cast shadows on the plate at the specimen's foot, highlights, +-10 % exposure,
        # JPEG): the foot tangents where shadows touch the outline (session 10, nothing chosen on it)
        "drifth_br11": dict(base, seed=101, specimen="aaa-11+branch", true_angles_deg=drift_angles(n, 105), hard=True),
    }


def with_audit(s, truth, sd=0.03, seed=0):
    """``s`` with an emulated angle audit in ``s.raw['capture']['audit']`` (in memory)."""
    cmd = np.array([v.angle_deg for v in s.views])
    true = np.array([v.get("true_angle_deg", v["angle_deg"]) for v in truth["views"]])
    err = true - cmd + np.random.default_rng(seed).normal(0.0, sd, len(cmd))
    err -= err[0]
    s.raw["capture"] = {"audit": [{"commanded_deg": float(a), "measured_deg": float(a + e), "error_deg": float(e)}
                                  for a, e in zip(cmd, err)]}
    return s


def _rot_err(Ra, Rb):
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


def _elev_t(R):
    """The optical axis's angle below the table plane, degrees."""
    return float(np.degrees(np.arcsin(-R[2, 2])))


def _elev(cam):
    return _elev_t(cam.R)


def _cyl(c):
    return np.array([np.hypot(c[0], c[1]), c[2]])


def main(argv=None):
    from organlab.calibration import calibration_for
    from organlab.poses import refine_poses
    from organlab.session import load_session
    from organlab.silhouette import SilhouetteModel
    from organlab.synthetic import make_session

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/organlab_bench_poses"))
    ap.add_argument("--scenes", nargs="+", default=list(scenes()) + ["drift_dented+audit", "drift_aaa7+audit", "sample"])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--voxel-size", type=float, default=None)
    ap.add_argument("--supersample", type=int, default=2,
                    help="sub-pixel samples per axis of the view and background renders (box filter; a real sensor "
                         "integrates over the pixel's area); renders at other than 2 go to their own folders")
    a = ap.parse_args(argv)
    if a.supersample < 1:
        ap.error(f"--supersample must be >= 1, got {a.supersample}")
    tag = "" if a.supersample == 2 else f"_ss{a.supersample}"  # the folders of 2 (the default) keep their old names
    for name in a.scenes:
        base_name, audit = name.split("+")[0], name.endswith("+audit")
        if name == "sample":
            folder = Path(__file__).resolve().parents[1] / "sample_sessions" / "aaa_phantom"
            truth = None
        else:
            folder = a.cache / f"{base_name}_36{tag}"
            if not (folder / "truth.json").is_file():
                t0, c0 = time.perf_counter(), time.process_time()
                make_session(folder, **scenes(supersample=a.supersample)[base_name])
                print(f"rendered {folder} in {time.perf_counter() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU")
            truth = json.loads((folder / "truth.json").read_text())
        s = load_session(folder)
        if audit:
            with_audit(s, truth)
        cal, _ = calibration_for(s)
        model = SilhouetteModel.from_session(s)
        sils = model.silhouettes()
        times = []
        for _ in range(max(1, a.repeat)):
            t0, c0 = time.perf_counter(), time.process_time()
            r = refine_poses(s, cal, sils, mode="on", images=model.images, background=model.background)
            times.append((time.perf_counter() - t0, time.process_time() - c0))
        wall, cpu = min(times)
        print(f"{name}: {wall:.2f} s wall, {cpu:.2f} s CPU; largest view residual before {np.nanmax(r.before_px):.3f} px; {r.reason}")
        if truth is not None:
            cmd = np.array([v.angle_deg for v in s.views])
            true = np.array([v.get("true_angle_deg", v["angle_deg"]) for v in truth["views"]])
            B = cal.turntable.camera.R
            used = np.array([np.degrees(np.arctan2((B.T @ c.R)[1, 0], (B.T @ c.R)[0, 0])) for c in r.cameras])
            e0 = np.abs(cmd - true)
            diff = (used - true + 180.0) % 360.0 - 180.0
            e1 = np.abs(diff)
            em = np.abs(diff - np.median(diff))  # modulo a common turn (the specimen's orientation on the plate)
            Rt, tt = np.array(truth["views"][0]["R"]), np.array(truth["views"][0]["t"])
            ct = -Rt.T @ tt
            cc, cr = cal.cameras(s)[0].center, r.cameras[0].center
            print(f"  angle error median/max {np.median(e0):.3f}/{e0.max():.3f} -> {np.median(e1):.3f}/{e1.max():.3f} deg "
                  f"(modulo a common turn {np.median(em):.3f}/{em.max():.3f}); camera centre error {np.linalg.norm(cc - ct):.2f} -> {np.linalg.norm(cr - ct):.2f} mm "
                  f"(modulo a turn about the axis {np.linalg.norm(_cyl(cc) - _cyl(ct)):.2f} -> "
                  f"{np.linalg.norm(_cyl(cr) - _cyl(ct)):.2f} mm); slip {r.slip}; candidates {r.gate.get('candidates')}")
            # against the cameras that rendered the views (for a bumped camera the table angles are right but
            # every view turned with the camera): each view's rotation error, and the camera's distance to the
            # axis, height and elevation (what the plate's rim measures)
            rot0 = [_rot_err(c.R, np.array(v["R"])) for c, v in zip(cal.cameras(s), truth["views"])]
            rot1 = [_rot_err(c.R, np.array(v["R"])) for c, v in zip(r.cameras, truth["views"])]
            rho_t = np.hypot(*ct[:2])
            print(f"  view rotation error median/max {np.median(rot0):.3f}/{np.max(rot0):.3f} -> {np.median(rot1):.3f}/{np.max(rot1):.3f} deg; "
                  f"distance to the axis {np.hypot(*cc[:2]) - rho_t:+.2f} -> {np.hypot(*cr[:2]) - rho_t:+.2f} mm "
                  f"(scale {np.hypot(*cr[:2]) / rho_t:.5f}), height {cc[2] - ct[2]:+.2f} -> {cr[2] - ct[2]:+.2f} mm, "
                  f"elevation {_elev(cal.cameras(s)[0]) - _elev_t(Rt):+.3f} -> {_elev(r.cameras[0]) - _elev_t(Rt):+.3f} deg; plate {r.plate}")
        if a.voxel_size:
            from organlab.pipeline import reconstruct

            vols = {}
            for mode in ("off", "auto", "on"):
                t0 = time.perf_counter()
                rep = reconstruct(s, voxel_size=a.voxel_size, refine_poses=mode).report
                vols[mode] = rep["mesh_volume_mm3"]
                err = rep.get("mesh_volume_error_pct")
                print(f"  {a.voxel_size:g} mm, --refine-poses {mode}: mesh volume "
                      + (f"{err:+.2f} % " if err is not None else f"{rep['mesh_volume_mm3']:.0f} mm3 ")
                      + f"({rep['poses']['reason'][:60]}; {time.perf_counter() - t0:.0f} s)")
            print(f"  volume change by the refinement: auto {100 * (vols['auto'] / vols['off'] - 1):+.3f} %, "
                  f"on {100 * (vols['on'] / vols['off'] - 1):+.3f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
