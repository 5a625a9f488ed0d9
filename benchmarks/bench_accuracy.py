"""Volume accuracy and time of the whole pipeline on the sample session.

Prints, for 1 mm and 2 mm voxels and for both hull tests (the thesis's 8-corner
box test and organlab's sub-voxel hull), the voxel and mesh volume errors
against the phantom's exact volume and the time of each stage, once with the
cameras calibrated from the session's images and once with the true cameras
from ``truth.json``.  Run: ``.venv/bin/python benchmarks/bench_accuracy.py``.
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
        print(f"{'cameras':<11} {'hull':<9} {'voxel':>6} {'voxel vol err':>14} {'mesh vol err':>13}  timings (s)")
        for label, root in sessions.items():
            for hull in ("subvoxel", "thesis"):
                for vs in (1.0, 2.0):
                    rec = reconstruct(load_session(root), voxel_size=vs, hull=hull)
                    r = rec.report
                    t = ", ".join(f"{k} {v:.2f}" for k, v in r["timings_s"].items())
                    print(f"{label:<11} {hull:<9} {vs:>4g}mm {r['volume_error_pct']:>+13.2f}% {r['mesh_volume_error_pct']:>+12.2f}%  {t}")


if __name__ == "__main__":
    main()
