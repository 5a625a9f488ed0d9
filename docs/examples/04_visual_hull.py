"""04 -- The visual hull, stage by stage: the whole pipeline as a notebook writes it.

    python docs/examples/04_visual_hull.py [SESSION] [VOXEL_MM]
"""

import sys
from pathlib import Path

import organlab as ol

SAMPLE = Path(__file__).resolve().parents[2] / "sample_sessions" / "aaa_phantom"


def main(session: Path = SAMPLE, voxel_size: float = 2.0) -> None:
    s = ol.load_session(session)
    cal = ol.calibrate(s)
    sils = ol.silhouettes(s, threshold=None)
    grid = ol.VoxelGrid.from_session(s, voxel_size=voxel_size)
    field = ol.hull_field(sils, cal.cameras(s), grid, sparse=True)  # sub-voxel hull, kept in a band about the surface
    raw = ol.mesh_from_field(field, grid)  # marching cubes between voxel centres
    mesh, steps = ol.finish_surface(raw, voxel_size=voxel_size)  # repaired and remeshed for FEA
    print(f"smallest angle {steps['raw']['min_angle_deg']:.3f} deg -> {steps['final']['min_angle_deg']:.1f} deg")
    m = ol.measure(mesh)
    print(f"grid {grid.shape} at {voxel_size:g} mm; mesh {m.n_faces} faces, watertight {m.watertight}")
    print(f"volume {m.volume_mm3:.0f} mm3, area {m.area_mm2:.0f} mm2")
    ref = s.reference.get("volume_mm3")
    if ref:
        print(f"volume error {100 * (m.volume_mm3 / ref - 1):+.2f} % against the reference {ref:.0f} mm3")


if __name__ == "__main__":
    main(*(f(a) for f, a in zip((Path, float), sys.argv[1:])))
