"""Warnings that do not cry wolf (issue 25, finding 4).

The docs' simulated capture (docs/capture.md: ``organlab capture --turntable sim --step 90
--sim-size 320x240``, 4 views) used to warn "3 of 4 views disagree" on a correct capture at
2 mm: the finished surface rounds off the edges 4 views leave sharp and loses up to 4 px of
these small silhouettes, which is resolution, not views that disagree.  The disagreement is
now measured on the surface the views carved (before finishing) and its limit scales with
the outline (see organlab.agreement); the causes a warning names fit the session.
"""

import json
import shutil

import numpy as np
import pytest

from organlab.agreement import likely_causes, view_agreement, worst_views
from organlab.cli import main
from organlab.pipeline import reconstruct


@pytest.fixture(scope="module")
def sim_capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("simcap") / "s"
    assert main(["capture", "--turntable", "sim", "--step", "90", "--out", str(root), "--background", "2",
                 "--sim-size", "320x240", "--quiet"]) == 0
    from organlab.calibration import calibrate
    from organlab import load_session

    calibrate(load_session(root)).save(root / "calibration.json")
    return root


def _mislabel(src, dest, image, angle):
    shutil.copytree(src, dest)
    doc = json.loads((dest / "session.json").read_text())
    for v in doc["views"]:
        if v["image"] == image:
            v["angle_deg"] = angle
    (dest / "session.json").write_text(json.dumps(doc))
    return dest


@pytest.mark.slow
def test_the_docs_simulated_capture_is_quiet_and_a_15_degree_mislabel_is_flagged(sim_capture, tmp_path):
    # 2 mm, where issue 15's limit cried wolf (3 of 4 views); 1 mm measured alike (0 px correct, the mislabel
    # 0.078 px of outline width), not run here to keep the suite short (45 s more)
    voxel = 2.0
    ok = reconstruct(sim_capture, voxel_size=voxel).report
    # measured (2 mm and 1 mm): no pixel of any view unexplained beyond the outline tolerance by the carved
    # surface (before: 0.43-1.21 % of 3 of the 4 silhouettes at 2 mm, by the finished surface)
    assert ok["warnings"] == [], ok["warnings"]
    assert max(v["agreement"]["disagreement"] for v in ok["views"]) == 0.0
    bad = reconstruct(_mislabel(sim_capture, tmp_path / "mis", "views/090.png", 105.0), voxel_size=voxel).report
    # view 090 labelled 105 degrees: with 4 views the opposite view (270, the same outline mirrored) carries
    # the contradiction: measured 24 px = 0.093 px of outline width (limit 0.05; 0.90 % of its silhouette)
    flagged = [v["image"] for v in bad["views"] if not v["agreement"]["ok"]]
    assert flagged and set(flagged) <= {"views/090.png", "views/270.png"}, flagged
    assert len(bad["warnings"]) == 1 and "wrong angle label" in bad["warnings"][0]
    # no angle suggested: the hull of the 3 other views (the mislabelled one among them) explains views/270.png
    # poorly at any angle (measured IoU 0.857 at 289 degrees, a wrong suggestion before min_iou)
    assert "agrees best" not in bad["warnings"][0]


def _ball_views(n=8, size=(160, 120)):
    from organlab.synthetic import Sphere, default_camera, render_masks

    ball = Sphere(center=(0.0, 0.0, 40.0), radius=25.0)
    table = default_camera(size)
    cams = [table.at_table_angle(a) for a in np.arange(n) * 360.0 / n]
    return ball, cams, render_masks(ball, cams, supersample=2)


def test_causes_fit_the_session():
    """A view whose silhouette was taken elsewhere than its pose says: with given cameras the warning
    names the camera file, not a turntable or table angles; with a turntable it names the angle."""
    from organlab.carving import hull_field
    from organlab.grid import VoxelGrid
    from organlab.surface import mesh_from_field
    from organlab.synthetic import Sphere, render_masks

    _, cams, cov = _ball_views()
    moved = Sphere(center=(8.0, 0.0, 40.0), radius=25.0)  # the specimen moved 8 mm before view 3
    cov = list(cov)
    cov[3] = render_masks(moved, [cams[3]], supersample=2)[0]
    grid = VoxelGrid.from_roi((-45, -45, 5), (45, 45, 75), 2.0)
    mesh = mesh_from_field(hull_field(cov, cams, grid, sparse=True), grid)
    given = view_agreement(mesh, cams, cov, voxel_size=2.0, turntable=[False] * 8)
    table = view_agreement(mesh, cams, cov, voxel_size=2.0)
    # measured: views[3] 9 px beyond the tolerance (0.20 px of outline width), 4 of 8 views over the limit
    assert given.worst[0] == 3 and not given.views[3]["ok"]
    assert "camera file" in given.warnings[0] and "turntable" not in given.warnings[0] and "angle" not in given.warnings[0]
    assert "wrong angle label" in table.warnings[0]
    assert "turntable" in likely_causes(True, True) and "turntable" not in likely_causes(True, False)


def test_one_ranking_of_the_worst_view():
    rows = [{"disagreement": 0.0, "iou": 0.95}, {"disagreement": 0.01, "iou": 0.99}, {"disagreement": 0.0, "iou": 0.90}]
    assert worst_views(rows) == [1, 2, 0]
