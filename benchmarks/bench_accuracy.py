"""Volume accuracy and time of the whole pipeline on the sample session.

Prints, for 1 mm and 2 mm voxels and for both hull tests (the thesis's 8-corner
box test and organlab's sub-voxel hull), the volume errors against the
phantom's exact volume of the voxels, of the raw marching-cubes mesh and of the
finished mesh (:func:`organlab.surface.finish_surface`: repaired, smoothed,
remeshed; the mesh ``organlab reconstruct`` writes by default), and the time
of each stage, once with the cameras calibrated from the session's images and
once with the true cameras from ``truth.json``.  Then the same volume errors
of the sub-voxel hull of the exact silhouettes (coverage rendered from the
phantom, true cameras): the visual hull's own excess over the specimen.
Run: ``.venv/bin/python benchmarks/bench_accuracy.py`` (about 1 min on 2 cores).
"""

import shutil
import tempfile
from pathlib import Path

from organlab import load_session
from organlab.pipeline import reconstruct
from organlab.synthetic import with_true_cameras

SAMPLE = Path(__file__).resolve().parents[1] / "sample_sessions" / "aaa_phantom"


def main():
    with tempfile.TemporaryDirectory() as tmp:
        calibrated = Path(tmp) / "calibrated"
        shutil.copytree(SAMPLE, calibrated, ignore=shutil.ignore_patterns("calibration.json", "calibration_check"))
        sessions = {"calibrated": calibrated, "true": with_true_cameras(SAMPLE, Path(tmp) / "true_cameras")}
        print(f"{'cameras':<11} {'hull':<9} {'voxel':>6} {'voxel vol err':>14} {'raw mesh err':>13} "
              f"{'finished err':>13}  timings (s)")
        for label, root in sessions.items():
            for hull in ("subvoxel", "thesis"):
                for vs in (1.0, 2.0):
                    rec = reconstruct(load_session(root), voxel_size=vs, hull=hull)
                    r = rec.report
                    ref = r["reference"]["volume_mm3"]
                    raw = 100.0 * (r["raw_mesh_volume_mm3"] - ref) / ref  # marching cubes, before finish_surface
                    t = ", ".join(f"{k} {v:.2f}" for k, v in r["timings_s"].items())
                    print(f"{label:<11} {hull:<9} {vs:>4g}mm {r['volume_error_pct']:>+13.2f}% {raw:>+12.2f}% "
                          f"{r['mesh_volume_error_pct']:>+12.2f}%  {t}", flush=True)
        exact_silhouettes(sessions["true"])


def exact_silhouettes(root):
    """The hull of the rendered (exact, noise-free) silhouettes: raw and finished mesh volume errors."""
    from organlab.synthetic._render import coverage
    from organlab.carving import hull_field
    from organlab.grid import VoxelGrid
    from organlab.pipeline import session_cameras
    from organlab.surface import finish_surface, mesh_from_field
    from organlab.synthetic import AAAPhantom

    s = load_session(root)
    cams = session_cameras(s)
    phantom = AAAPhantom()
    covs = [coverage(c, phantom, supersample=4) for c in cams]  # 16 rays per pixel
    ref = s.reference["volume_mm3"]
    print("\nexact silhouettes (rendered coverage), true cameras, sub-voxel hull:")
    print(f"{'voxel':>6} {'raw mesh err':>13} {'finished err':>13}")
    for vs in (1.0, 2.0):
        grid = VoxelGrid.from_session(s, vs)
        raw = mesh_from_field(hull_field(covs, cams, grid, sparse=True), grid)
        finished, _ = finish_surface(raw, voxel_size=vs)
        print(f"{vs:>4g}mm {100 * (raw.volume - ref) / ref:>+12.2f}% {100 * (finished.volume - ref) / ref:>+12.2f}%",
              flush=True)


if __name__ == "__main__":
    main()
