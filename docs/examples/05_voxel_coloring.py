"""05 -- Voxel colouring (Seitz & Dyer) on the visual hull: colours, and what the hull alone keeps.

    python docs/examples/05_voxel_coloring.py [SESSION] [VOXEL_MM]
"""

import sys
from pathlib import Path

import organlab as ol

SAMPLE = Path(__file__).resolve().parents[2] / "sample_sessions" / "aaa_phantom"


def main(session: Path = SAMPLE, voxel_size: float = 2.0) -> None:
    s = ol.load_session(session)
    cameras = ol.calibrate(s).cameras(s)
    images = s.images()
    sils = ol.silhouettes(s, images=images)
    grid = ol.VoxelGrid.from_session(s, voxel_size=voxel_size)
    hull = ol.carve(sils, cameras, grid)  # the thesis's bounding-box test
    res = ol.color_voxels(images, cameras, hull, grid, masks=[x.mask for x in sils])
    print(f"hull {grid.volume_of(hull):.0f} mm3 -> coloured model {grid.volume_of(res.occupancy):.0f} mm3")
    print(f"{int(res.colored.sum())} voxels coloured; mean colour {res.colors[res.colored].mean(0).round(1).tolist()}")


if __name__ == "__main__":
    main(*(f(a) for f, a in zip((Path, float), sys.argv[1:])))
