"""01 -- Load a session folder and look at what it holds.

    python docs/examples/01_session.py [SESSION]
"""

import sys
from pathlib import Path

import organlab as ol

SAMPLE = Path(__file__).resolve().parents[2] / "sample_sessions" / "aaa_phantom"


def main(session: Path = SAMPLE) -> None:
    s = ol.load_session(session)  # checks every key and image; one clear line when something is wrong
    print(f"{s.name}: {len(s.views)} views of {s.image_size[0]}x{s.image_size[1]} px, "
          f"{len(s.intrinsic_images)} intrinsic and {len(s.turntable_images)} turntable board images, "
          f"{len(s.background_images)} background frames")
    print(f"angles {s.views[0].angle_deg:g} .. {s.views[-1].angle_deg:g} deg; roi {s.roi_min.tolist()} .. {s.roi_max.tolist()} mm")
    first = s.images()[0]
    print(f"first view: {first.shape} {first.dtype}, mean colour {first.reshape(-1, 3).mean(0).round(1).tolist()}")


if __name__ == "__main__":
    main(*(Path(a) for a in sys.argv[1:]))
