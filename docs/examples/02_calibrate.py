"""02 -- Calibrate the camera and the turntable from the board images; save and draw the check figures.

    python docs/examples/02_calibrate.py [SESSION] [OUT]
"""

import sys
from pathlib import Path

import organlab as ol
from organlab.figures import check_figures

SAMPLE = Path(__file__).resolve().parents[2] / "sample_sessions" / "aaa_phantom"


def main(session: Path = SAMPLE, out: Path = Path("example_out")) -> None:
    s = ol.load_session(session)
    cal = ol.calibrate(s)  # intrinsics (Bouguet model) + turntable (camera pose and axis); writes nothing
    for line in cal.summary():
        print(line)
    out.mkdir(parents=True, exist_ok=True)
    path = cal.save(out / "calibration.json")
    figures = check_figures(s, cal, out / "calibration_check")
    again = ol.Calibration.load(path)
    print(f"saved {path}; {len(figures)} check figures; reloaded matches the session: {again.mismatch(s) == []}")
    cam = again.cameras(s)[9]
    print(f"view 9 ({s.views[9].angle_deg:g} deg): camera centre {cam.center.round(2).tolist()} mm")


if __name__ == "__main__":
    main(*(Path(a) for a in sys.argv[1:]))
