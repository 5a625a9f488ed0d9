"""Issue 20 (a): a table that lost steps, corrected from the silhouettes of a specimen whose outline shows its angles.

``aaa-11+branch`` (:class:`organlab.synthetic.BranchedAAA`): an AAA of the sample's family with another shape and
two renal-artery-like stumps near its top.  A plain AAA is near symmetric about the table axis (its drift moves
its outline by less than 0.2 px: the gate refuses, docs/trust.md); the stumps show the angles, and its visual
hull is near its volume (no hidden concavity, unlike ``dented``).  The refined angles are scored against the
angles that rendered the views (``truth.json``), the volume against the specimen's exact volume.
"""

import json

import numpy as np
import pytest

from organlab.synthetic import AAAPhantom, BranchedAAA, make_specimen

#: Cheaper than the issue's 36 views of 640 x 480 (bench_poses.py, since the trend + jitter prior: drift_br11 0.112 /
#: 0.541 degrees, driftb_br11 0.100 / 0.420, driftc_br11 0.131 / 0.332, driftd_br11 0.119 / 0.382; docs/trust.md):
#: 480 x 360, where the stumps' outline moves 3/4 as many px per degree.  Measured on this render: 36 views 480 x 360
#: applied, 0.168 / 0.852 degrees (0.211 / 0.836 with the former prior, second differences sd 0.5); before that prior:
#: 24 views 480 x 360 0.324 / 1.869; 320 x 240 (24 or 36 views) refused by the gate (left-out views 0.141 -> 0.105 px,
#: 0.036 px < the 0.05 px gain needed)
SCENE = dict(image_size=(480, 360), n_views=36)
#: measured 0.112 degrees (1.54 before; 0.139 with the foot tangents left out, until 2026-12-04; 0.168 with the
#: outline's 0.5-crossing points; 0.211 with the former prior)
MEDIAN_DEG = 0.3
#: measured 0.548 degrees (3.38 before; 0.844 with the foot tangents left out; 0.852 with the 0.5-crossing points; 0.836
#: with the former prior): a view's own tangents pin its angle to 0.17-0.27
#: degrees RMS at 640 x 480 (docs/trust.md), about as much as the 0.3 degrees of jitter, and less at 480 x 360
MAX_DEG = 1.0
#: 2 mm hull (refined cameras) against the exact volume: measured -0.95 % (true cameras' hull -0.93 %: the
#: 2 mm hull's own error at 480 x 360; the issue's 0.5 % is at 1 mm, 640 x 480: -0.08 %, docs/trust.md)
VOLUME_TOL = 0.015
#: ... against the true cameras' hull (what the poses cost): measured -0.019 % (-0.031 % with the former prior;
#: calibrated cameras -0.12 %)
POSE_VOLUME_TOL = 0.0008


def test_branched_aaa_volume_is_exact():
    """The stumps' volume outside the aorta (capsule minus its part inside, by quadrature) against Monte Carlo."""
    b, a = make_specimen("aaa-11+branch"), make_specimen("aaa-11")
    assert isinstance(b, BranchedAAA) and isinstance(a, AAAPhantom) and b.name == "aaa-11+branch"
    extra = [st.volume - st.overlap(b.star) for st in b.stumps]
    assert abs(b.volume - a.volume - sum(extra)) < 1e-6
    # the quadrature has converged (measured: 24 x 64 against 48 x 128 nodes, 1e-13 mm^3 apart)
    assert all(abs(st.overlap(b.star) - st.overlap(b.star, 48, 128)) < 1e-9 for st in b.stumps)
    rng = np.random.default_rng(7)
    n = 400_000
    for st, ex in zip(b.stumps, extra):
        # uniform samples in the stump's box (its frame), inside the branched solid but not the plain AAA
        e, ez = st.e, np.array([0.0, 0.0, 1.0])
        ep = np.cross(ez, e)
        x = rng.random((n, 3))
        s = st.s0 + x[:, 0] * (st.s1 + st.radius - st.s0)
        u, v = (2 * x[:, 1] - 1) * st.radius, (2 * x[:, 2] - 1) * st.radius
        p = s[:, None] * e + u[:, None] * ep + (st.z + v)[:, None] * ez
        f = np.mean(b.inside(p) & ~a.inside(p))
        box = (st.s1 + st.radius - st.s0) * 4 * st.radius**2
        sd = np.sqrt(f * (1 - f) / n) * box
        # measured (5 x 4e6 samples): 419.60 +- 0.10 against 419.52, 313.58 +- 0.08 against 313.68 mm^3
        assert abs(f * box - ex) < 4 * sd, (f * box, ex, sd)
    # rays: every first hit lies on the union's boundary (just before it outside, just after it inside)
    from organlab.synthetic import default_camera

    cam = default_camera((320, 240)).at_table_angle(35.0)
    uv = np.stack(np.meshgrid(np.arange(100.0, 220.0, 0.5), np.arange(20.0, 60.0, 0.5)), -1).reshape(-1, 2)
    d = np.column_stack([(uv - cam.K[:2, 2]) / np.diag(cam.K)[:2], np.ones(len(uv))]) @ cam.R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, nrm = b.intersect(np.broadcast_to(cam.center, d.shape), d)
    hit = np.isfinite(t)
    q = cam.center + t[hit, None] * d[hit]
    stump_hits = np.zeros(hit.sum(), bool)
    for st in b.stumps:
        stump_hits |= st._inside(q + 1e-3 * d[hit]) & ~a.inside(q + 1e-3 * d[hit])
    assert stump_hits.sum() > 10  # the top's rays see the stumps (18 of them)
    assert b.inside(q + 1e-4 * d[hit]).all() and not b.inside(q - 1e-4 * d[hit]).any()
    assert np.allclose(np.linalg.norm(nrm[hit], axis=1), 1.0) and (np.einsum("ij,ij->i", nrm[hit], d[hit]) < 0).all()
    with pytest.raises(ValueError, match="90 degrees apart"):
        BranchedAAA(shape_seed=11, branches=((80.0, 165.0, 3.0, 15.0), (120.0, 164.0, 3.0, 15.0)))


def _drift(n, seed, total=3.0, jitter=0.3):
    """True table angles drifting linearly to ``total`` degrees over the turn, plus ``jitter`` degrees per stop."""
    g = np.random.default_rng(seed)
    return 360.0 * np.arange(n) / n + total * np.arange(n) / (n - 1) + np.concatenate([[0.0], g.normal(0, jitter, n - 1)])


@pytest.mark.slow
def test_drifting_table_on_a_branched_aaa_is_corrected(tmp_path):
    from organlab.calibration import calibration_for
    from organlab.carving import hull_field
    from organlab.grid import VoxelGrid
    from organlab.poses import refine_poses
    from organlab.session import load_session
    from organlab.silhouette import SilhouetteModel
    from organlab.surface import mesh_from_field
    from organlab.synthetic import make_session

    from tests._shared_data import POSE_SCENE

    n = SCENE["n_views"]
    true = _drift(n, 55)  # a render and a drift the benchmark's scenes (drift_br11, driftb_br11) did not use
    make_session(tmp_path, **dict(POSE_SCENE, **SCENE), seed=51, specimen="aaa-11+branch", true_angles_deg=true)
    s = load_session(tmp_path)
    cal, _ = calibration_for(s)
    model = SilhouetteModel.from_session(s)
    sils = model.silhouettes()
    truth = json.loads((tmp_path / "truth.json").read_text())
    cmd = np.array([v.angle_deg for v in s.views])
    assert np.allclose([v["true_angle_deg"] for v in truth["views"]], true)
    e0 = np.abs(cmd - true)
    assert np.median(e0) > 1.0 and e0.max() > 2.5  # measured 1.54 / 3.38 degrees

    r = refine_poses(s, cal, sils, mode="auto", images=model.images, background=model.background)
    assert r.flagged and r.accepted and r.gate["refined"] == "angles", r.reason
    B = cal.turntable.camera.R
    used = np.array([np.degrees(np.arctan2((B.T @ c.R)[1, 0], (B.T @ c.R)[0, 0])) for c in r.cameras])
    e1 = np.abs((used - true + 180.0) % 360.0 - 180.0)
    assert np.median(e1) <= MEDIAN_DEG and e1.max() <= MAX_DEG, (np.median(e1), e1.max())
    # each view's angle sd (relative to view 0, from the fit's normal equations) against its error relative to
    # view 0: errors / sd RMS measured 1.04-1.90 on six 640 x 480 drifts (docs/trust.md, session 10), here 1.22, sd
    # median 0.148 degrees (1.04 and 0.24 with the foot tangents left out; 1.27 with the outline's 0.5-crossing
    # points): the bound fails when the sd is off by 2x
    sd = r.angle_sd_deg
    rel = (used - true + 180.0) % 360.0 - 180.0
    z = (rel[1:] - rel[0]) / sd[1:]
    assert sd[0] == 0.0 and np.all(np.isfinite(sd[1:]) & (sd[1:] > 0)), sd
    assert 0.5 < np.sqrt(np.mean(z**2)) < 2.0, np.sqrt(np.mean(z**2))
    assert [v["angle_sd_deg"] for v in r.to_dict()["views"]][1:] == [round(float(v), 4) for v in sd[1:]]

    # the volume: 2 mm hulls of the same silhouettes, against the specimen's exact volume and the true cameras' hull
    from organlab.camera import Camera

    grid = VoxelGrid.from_session(s, 2.0)
    cam = cal.camera
    true_cams = [Camera(cam.K, cam.dist, np.array(v["R"]), np.array(v["t"]), image_size=cam.image_size) for v in truth["views"]]
    vol, vol_true, vol_cal = (mesh_from_field(hull_field(sils, cs, grid, sparse=True), grid).volume
                              for cs in (r.cameras, true_cams, cal.cameras(s)))
    exact = make_specimen("aaa-11+branch").volume
    assert abs(vol / exact - 1) < VOLUME_TOL, vol / exact - 1
    assert abs(vol / vol_true - 1) < POSE_VOLUME_TOL, vol / vol_true - 1
    assert abs(vol_cal / vol_true - 1) > abs(vol / vol_true - 1)


def test_trend_jitter_prior_is_the_marginal_of_its_model():
    """The angles' prior (a trend plus each stop's own error, the trend integrated out) against the same marginal
    computed the long way: the inverse of the covariance trend + jitter, the trend's level and slope given a
    vanishing precision (1e-9) instead of none."""
    from organlab.poses._model import trend_jitter_root

    n, st, sj = 36, 0.05, 0.3
    S = trend_jitter_root(n, st, sj)
    D = np.diff(np.eye(n), 2, axis=0)
    cov = np.linalg.inv(D.T @ D / st**2 + 1e-9 * np.eye(n)) + sj**2 * np.eye(n)
    P = np.linalg.inv(cov)
    # measured 1.8e-5 apart (the 1e-9 standing in for none), entries up to 9.47 (0.3^-2 less what the trend takes)
    assert np.abs(S.T @ S - P).max() < 1e-5 * np.abs(P).max()
    # a straight drift costs nothing, a lone stop's error about (error / sd)^2 (measured 0.85 for 1 sd)
    assert np.sum((S @ np.linspace(0.0, 3.0, n)) ** 2) < 1e-9
    e = np.zeros(n)
    e[10] = sj
    assert 0.7 < np.sum((S @ e) ** 2) < 1.0


def test_plate_rim_offsets_do_not_see_a_turn_about_the_axis():
    """The plate's rim (organlab/poses/_plate.py) is measured along the normals of its image, so a turn of the
    camera about the table axis, which changes no image of the round plate, leaves its offsets as they were.
    Until 2026-12-03 the offsets were taken along the image of the radial direction, oblique to the rim's image
    (up to 36 degrees here): a turn slid the rim's points along it and changed the offsets to first order, so
    the joint fit with the tangents held the unseen turn where the rim happened to be measured."""
    from organlab.poses._plate import Rim, _rim_geometry
    from organlab.synthetic import default_camera

    cam = default_camera((640, 480))
    radius = 125.0
    p, nrm, _ = _rim_geometry(cam, radius, 0.0, 10.0)
    th = np.linspace(0.0, 2 * np.pi, len(p), endpoint=False)
    # perpendicular to the projected rim (its chord at the neighbouring points); measured 1.2e-5
    chord = np.roll(p, -1, axis=0) - np.roll(p, 1, axis=0)
    chord /= np.linalg.norm(chord, axis=1, keepdims=True)
    assert np.abs(np.einsum("ij,ij->i", chord, nrm)).max() < 0.01
    # outward: the rim of a larger plate projects further along them
    wider = cam.project(np.stack([(radius + 1) * np.cos(th), (radius + 1) * np.sin(th), np.zeros(len(th))], 1))
    assert (np.einsum("ij,ij->i", wider - p, nrm) > 0).all()
    # edges found 0.3 px outside the rim at this camera; the same camera turned 0.2 degrees about the axis:
    # measured at most 0.0011 px of change (second order); along the radial direction's image 0.25 px
    rim = Rim(th, p + 0.3 * nrm, nrm, radius, 0.0)
    assert np.allclose(rim.residuals(cam), 0.3, atol=1e-6)
    turned = cam.at_table_angle(-0.2)
    assert np.abs(rim.residuals(turned) - 0.3).max() < 0.005
    out = cam.project(np.stack([(radius + 0.5) * np.cos(th), (radius + 0.5) * np.sin(th), np.zeros(len(th))], 1)) - p
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    oblique = Rim(th, p + 0.3 * out, out, radius, 0.0)
    assert np.abs(oblique.residuals(turned) - 0.3).max() > 0.1


def _disc_coverage(shape, centre, radius, ss=64):
    """Area coverage of a disc, ``(H, W)``, from ``ss x ss`` samples per pixel (position error ~1 / (2 ss^2) px)."""
    h, w = shape
    o = (np.arange(ss) + 0.5) / ss - 0.5
    ys, xs = (np.arange(h)[:, None] + o).ravel(), (np.arange(w)[:, None] + o).ravel()
    inside = (ys[:, None] - centre[1]) ** 2 + (xs[None, :] - centre[0]) ** 2 < radius**2
    return inside.reshape(h, ss, w, ss).mean(axis=(1, 3))


@pytest.mark.parametrize("centre", [(20.3, 19.71), (20.0, 20.0), (19.55, 20.42)])
def test_outline_points_from_the_profile_across_the_edge(centre, monkeypatch):
    """The tangents' outline points (``_tangents._profile_points``) where the coverage summed across the edge puts
    them, on a disc's exact area coverage: the hull's points lie on the disc's circle.  Measured: largest
    distance from it 0.010-0.014 px (RMS 0.005; the circle's curvature, a straight edge assumed); with the linear
    0.5-crossing instead 0.079-0.091 px (RMS 0.044-0.052): the bound fails if the profile is summed off by a pixel,
    or taken on the wrong side of the edge, or not used."""
    from organlab.poses import _tangents
    from organlab.poses._refine import _Intrinsics

    radius = 12.37
    cov = _disc_coverage((40, 40), centre, radius)
    cam = _Intrinsics(np.eye(3), np.zeros(5))  # normalised coordinates = pixels
    default = _tangents.PROFILE_HALF_PX
    far = {}
    for half in (0, default):
        monkeypatch.setattr(_tangents, "PROFILE_HALF_PX", half)
        rays, _ = _tangents.outline_rays(cov, cam)
        far[half] = np.abs(np.hypot(rays[:, 0] - centre[0], rays[:, 1] - centre[1]) - radius).max()
    assert default >= 2
    assert far[default] < 0.025 and far[0] > 0.06, far
