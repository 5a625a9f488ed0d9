"""06 -- The same in one call, and the files `organlab reconstruct` writes.

    python docs/examples/06_reconstruct.py [SESSION] [OUT]
"""

import json
import sys
from pathlib import Path

import organlab as ol
from organlab.pipeline import summary_table

SAMPLE = Path(__file__).resolve().parents[2] / "sample_sessions" / "aaa_phantom"


def main(session: Path = SAMPLE, out: Path = Path("example_out")) -> None:
    rec = ol.reconstruct(session, voxel_size=2.0)
    paths = ol.write_outputs(rec, out)
    print(summary_table(rec.report))
    print("wrote", ", ".join(sorted(p.name for p in paths.values())))
    report = json.loads(paths["report"].read_text())
    print(f"report.json: {len(report['views'])} views, calibration {report['calibration']['source']}")


if __name__ == "__main__":
    main(*(Path(a) for a in sys.argv[1:]))
