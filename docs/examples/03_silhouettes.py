"""03 -- Silhouettes by background subtraction: automatic (Li) and given thresholds.

    python docs/examples/03_silhouettes.py [SESSION]
"""

import sys
from pathlib import Path

import organlab as ol

SAMPLE = Path(__file__).resolve().parents[2] / "sample_sessions" / "aaa_phantom"


def main(session: Path = SAMPLE, threshold: float = 40.0) -> None:
    s = ol.load_session(session)
    images = s.images()  # read once, reuse for every threshold
    auto = ol.silhouettes(s, images=images)
    fixed = ol.silhouettes(s, images=images, threshold=threshold)
    for i in (0, 9, 18, 27):
        print(f"view {i:2d}: automatic threshold {auto[i].threshold:5.1f} -> {auto[i].mask.sum():6d} px;"
              f" threshold {threshold:g} -> {fixed[i].mask.sum():6d} px;"
              f" sub-pixel area {auto[i].coverage.sum():9.1f} px")


if __name__ == "__main__":
    main(*(Path(a) for a in sys.argv[1:]))
