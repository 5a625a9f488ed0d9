"""Issue 21 part 2: finish_surface stays on the raw surface and states how far it lies from it.

The figures are checked against a brute-force closest point (every face of the other surface), on
specimens the defaults never saw: a ball (radius 12 mm) alone, with a fin thinner than the remesh edge
(1.2 mm thick, 1 mm voxels, 1.5 mm edges), with a tilted pin 1.4 mm across, and with a curved shell
0.9 mm thick over its top.  Before the adaptive remeshing the fin was mostly removed (raw to finished:
mean 0.57, max 8.7 voxels); now every shape is within the issue's 0.25 voxel mean and 1 voxel max
(measured: ball 0.019 / 0.09, fin 0.022 / 0.49, pin 0.021 / 0.32, shell 0.031 / 0.48) with every angle
>= 20 degrees (38.0, 22.7, 29.1, 21.7).
"""

import numpy as np
import pytest

from organlab.grid import VoxelGrid
from organlab.surface import FinishedSurface, closest_points, finish_surface, mesh_from_field, surface_deviation
from organlab.surface._deviation import _tri_closest


def _field(kind):
    grid = VoxelGrid(origin=(-20.0, -20.0, -20.0), voxel_size=1.0, shape=(41, 41, 41))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    d = np.sqrt(x**2 + y**2 + z**2) - 12.0  # signed distance to the ball, mm
    if kind in ("fin", True):  # a plate 1.2 mm thick, 16 mm wide, out to x = 18 mm
        d = np.minimum(d, np.maximum.reduce([np.abs(z) - 0.6, np.abs(y) - 8.0, x - 18.0, -x]))
    elif kind == "pin":  # a rod 1.4 mm across, tilted, out to 19 mm from the centre
        a = np.array([0.8, 0.36, 0.48]) / np.linalg.norm([0.8, 0.36, 0.48])
        s = x * a[0] + y * a[1] + z * a[2]
        r = np.sqrt(np.maximum(x**2 + y**2 + z**2 - s**2, 0.0))
        d = np.minimum(d, np.maximum(r - 0.7, np.maximum(s - 19.0, -s)))
    elif kind == "shell":  # a spherical cap 0.9 mm thick (radius 17 mm about (0, 0, -4)) above z = 6 mm
        rr = np.sqrt(x**2 + y**2 + (z + 4.0) ** 2)
        d = np.minimum(d, np.maximum(np.abs(rr - 17.0) - 0.45, 6.0 - z))
    return np.clip(0.5 - d, 0.0, 1.0).astype(np.float32), grid  # a coverage-like field, its 0.5 level at d = 0


def _brute(points, mesh):
    v, f = mesh.vertices, mesh.faces
    return np.array([np.sqrt(((_tri_closest(np.repeat(p[None], len(f), 0), v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]) - p) ** 2)
                             .sum(1)).min() for p in points])


def test_closest_points_match_a_brute_force_search():
    field, grid = _field("fin")
    raw = mesh_from_field(field, grid)
    rng = np.random.default_rng(1)
    p = raw.vertices[rng.integers(0, len(raw.vertices), 200)] + rng.normal(0.0, 0.4, (200, 3))
    _, d = closest_points(p, raw)
    b = _brute(p, raw)
    # never nearer than the true nearest point; among 6 candidate triangles by centroid, a few points by
    # the fin's small marching-cubes triangles get a farther one (measured: 0.0041 mm at most, a few of 200)
    assert np.all(d >= b - 1e-9)
    np.testing.assert_allclose(d, b, atol=0.01)
    assert np.mean(np.abs(d - b) < 1e-9) > 0.9


SHAPES = ("ball", "fin", "pin", "shell")


@pytest.fixture(scope="module")
def finished():
    out = {}
    for kind in SHAPES:
        field, grid = _field(kind)
        raw = mesh_from_field(field, grid)
        out[kind] = raw, finish_surface(raw, voxel_size=1.0)
    return out


def test_finish_surface_is_typed_and_reports_its_deviation(finished):
    raw, res = finished["ball"]
    assert isinstance(res, FinishedSurface)
    d = res.to_dict()
    assert set(d) >= {"steps", "raw", "final", "watertight", "volume_change_pct", "deviation"}
    mesh, report = res  # the former (Mesh, dict) form
    assert mesh is res.mesh and report == d
    # the figures are what an independent search gives (finished vertices to the raw surface)
    sub = res.mesh.vertices[::25]
    brute = _brute(sub, raw)
    assert res.deviation["finished_to_raw"]["max_voxels"] >= brute.max() - 1e-6
    assert res.deviation == surface_deviation(res.mesh, raw, voxel_size=1.0)


def _views():
    """Three perspective views along the axes, 6 px per mm at the centre (the fin seen face-on first)."""
    from organlab.camera import Camera

    K = np.array([[900.0, 0.0, 160.0], [0.0, 900.0, 120.0], [0.0, 0.0, 1.0]])
    rots = (np.eye(3), np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]]), np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]))
    return [Camera(K, np.zeros(5), R, np.array([0.0, 0.0, 150.0]), (320, 240)) for R in rots]


@pytest.mark.parametrize("kind", SHAPES)
def test_thin_parts_stay_on_the_raw_surface(finished, kind):
    from organlab.raster import model_mask

    raw, res = finished[kind]
    assert res.watertight and res.final["min_angle_deg"] >= 20.0  # the FEA promises (measured 21.7-38.0)
    # the raw volume is restored (measured < 1e-4 %), with its parts thinner than 0.6 voxel made that thick
    # (._thin.thickened: the shell's cut edge, 59 vertices, +0.034 %; the others have none)
    thick = sum(st.get("vertices_thickened", 0) for st in res.steps)
    assert abs(res.volume_change_pct) < (0.1 if thick else 0.01), (thick, res.volume_change_pct)
    # issue 21's bounds, by brute force both ways on every 5th vertex (measured: raw to finished max 0.09-0.43
    # voxel, finished to raw max 0.05-0.15; the mean 0.02-0.03)
    r2f, f2r = _brute(raw.vertices[::5], res.mesh), _brute(res.mesh.vertices[::5], raw)
    assert r2f.mean() < 0.25 and f2r.mean() < 0.25
    assert r2f.max() < 1.0 and f2r.max() < 1.0
    # the report's figures cover what the brute force found (all vertices, and face centres)
    assert res.deviation["raw_to_finished"]["max_voxels"] >= r2f.max() - 1e-3
    assert res.deviation["max_voxels"] < 1.0 and res.deviation["mean_voxels"] < 0.25
    # the projections against the raw surface's own: each flipped boundary pixel counts here (the plain ball:
    # 21 px lost, 26 gained of 16 300, IoU 0.997), so this is stricter than the change of IoU
    # against a silhouette.  Measured 0.9956-0.9977, except where a thin part's rim, a crease of the raw
    # surface, is seen face-on: the fin 0.979 (its far end, 1.2 mm thick, is cut by 0.3 mm) and the shell from
    # below 0.990 (its cut edge): the remesher does not follow feature lines (snapping ridge vertices onto the
    # raw creases was tried: fin 0.981, shell 0.995, but slivers on the dino)
    missed = {("fin", 0): 0.975, ("shell", 0): 0.985}
    for i, cam in enumerate(_views()):
        a, b = model_mask(raw, cam, (240, 320)), model_mask(res.mesh, cam, (240, 320))
        iou = (a & b).sum() / (a | b).sum()
        assert iou > missed.get((kind, i), 0.995), (kind, i, iou)


def test_the_fin_was_cut_before_and_is_kept_now(finished):
    raw, res = finished["fin"]
    # the fin's far end (x = 18 mm) is still there (before issue 21: cut back by 8.7 voxels)
    assert res.mesh.vertices[:, 0].max() > 17.5
    # the fin (its corner where it leaves the ball included) is where the surface departs most (measured 0.49
    # voxel there, 0.31 on the ball), and its worst point is within a voxel of the raw
    _, d = closest_points(raw.vertices, res.mesh)
    fin = (np.abs(raw.vertices[:, 2]) < 1.0) & (raw.vertices[:, 0] > 10.0)
    assert d[fin].max() == pytest.approx(d.max()) and d.max() < 1.0


def test_the_report_states_the_deviation_and_the_worst_view_iou_change(small_session):
    from organlab.pipeline import reconstruct

    # at 1 mm, the voxel size issue 21's promise is stated at (at 2 mm the worst of these 6 views is -0.0019 on
    # today's code, -0.0011 earlier, -0.0023 while the rim step's last ring also took lone pixels: too close to
    # the bound at 2 mm for a test)
    rec = reconstruct(small_session, voxel_size=1.0)
    dev = rec.report["surface"]["deviation"]
    rows = [v["agreement"] for v in rec.report["views"]]
    change = [r["iou"] - r["raw_iou"] for r in rows]
    k = int(np.argmax(np.abs(change)))
    assert dev["worst_view_iou_change"] == pytest.approx(change[k], abs=1e-5)
    assert dev["worst_view"] == rec.report["views"][k]["image"]
    # the raw IoU is the raw mesh's own: re-rendered here
    from organlab.raster import model_mask

    cam, sil = rec.cameras[k], np.asarray(rec.silhouettes[k].coverage) >= 0.5
    r = model_mask(rec.raw_mesh, cam, sil.shape)
    assert rows[k]["raw_iou"] == pytest.approx((r & sil).sum() / (r | sil).sum(), abs=1e-9)
    # 6 views of the sample at 1 mm: measured mean 0.021, max 0.30 voxel, worst view IoU change -0.0012
    # (at 2 mm before issue 21's adaptive remeshing: 0.064, 1.99 voxels, -0.0089, the 3 mm edge rounded the neck off)
    assert 0 < dev["mean_voxels"] < 0.25 and dev["max_voxels"] < 1.0
    assert abs(dev["worst_view_iou_change"]) < 0.002


# ------------------------------------------------------------------ the last step: stay_on_data (_guard.py)
# A ball with thin fins (half a voxel to a voxel thick) at coarse voxels: the remesher's sliver clean-up flattens
# the fins' knife edges (faces folded back by more than 150 degrees, where no triangle of 20 degrees fits) and
# cuts out and fills what it still cannot fix, without projecting back: the fins' tips were shaved by up to 3.5
# voxels.  finish_surface's last step (``stay_on_data``, organlab/surface/_guard.py) puts the lost raw points back
# as vertices and pulls the vertices still more than 0.9 voxel off back onto the raw surface, keeping the angle.

def _finned_occupancy(voxel_size, seed, half=None):
    """A 15 mm ball with three half-discs of radius 24 mm, 1-2 voxels thick (random planes; ``half``: the
    half-thickness in voxels, all three): the occupancy and its grid."""
    n = int(60 / voxel_size) + 1
    grid = VoxelGrid(origin=(-30.0,) * 3, voxel_size=voxel_size, shape=(n, n, n))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    body = x**2 + y**2 + z**2 <= 15.0**2
    rng = np.random.default_rng(seed)
    for _ in range(3):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        e = np.cross(d, rng.normal(size=3))
        e /= np.linalg.norm(e)
        t = rng.uniform(0.5, 1.0) if half is None else half
        body |= ((np.abs(x * d[0] + y * d[1] + z * d[2]) <= t * voxel_size)
                 & (x**2 + y**2 + z**2 <= 24.0**2) & (x * e[0] + y * e[1] + z * e[2] > 0))
    return body, grid


def _finned_ball(voxel_size, seed, half=None):
    """The surface of :func:`_finned_occupancy`."""
    return mesh_from_field(*_finned_occupancy(voxel_size, seed, half))


def _without_thin(monkeypatch):
    """finish_surface as before the thin-part handling (._thin): no part thickened, no vertex put back after
    smoothing, every closest point taken by the remesher's projections, whichever side of a thin part it is on."""
    monkeypatch.setattr("organlab.surface._repair.keep_thin", lambda smoothed, raw, **kw: (smoothed, 0))
    monkeypatch.setattr("organlab.surface._repair.thickened", lambda raw, depth, min_mm, **kw: (raw, 0))
    monkeypatch.setattr("organlab.surface._remesh.SAME_SIDE", False)  # its projections' rule (compiled, not a call)


# measured (before -> after the last step): seed 0 at 2 mm 3.4555 -> 0.8392 voxels, seed 1 at 1.5 mm (a
# scene the step was not developed on) 1.0157 -> 0.7197; the smallest angles 20.23 and 20.48 degrees
@pytest.mark.parametrize("voxel_size, seed", [(2.0, 0), (1.5, 1)])
def test_finished_fins_stay_within_a_voxel(voxel_size, seed, monkeypatch):
    # the last step on the case it was made for: the thin-part handling (._thin) now keeps these fins within a voxel
    # before it (test_thin_parts_are_not_smoothed_through), so it is switched off here
    _without_thin(monkeypatch)
    raw = _finned_ball(voxel_size, seed)
    fin = finish_surface(raw, voxel_size=voxel_size)
    guard = [s for s in fin.steps if s["step"] == "stay_on_data"]
    # the case is real: without the last step the finished surface was more than a voxel off the raw one
    assert len(guard) == 1 and guard[0]["max_voxels"][0] > 1.0, fin.steps
    assert guard[0]["vertices_inserted"] > 0
    # the promise, measured again here independently of the report (against the raw surface less its specks)
    from organlab.surface._repair import repair_mesh

    repaired, _ = repair_mesh(raw, speck_mm=3.0 * voxel_size)
    dev = surface_deviation(fin.mesh, repaired, voxel_size=voxel_size)
    assert dev["max_voxels"] < 1.0 and dev["mean_voxels"] < 0.25, dev
    assert dev == {k: fin.deviation[k] for k in dev}
    # the FEA promises still hold
    assert fin.watertight and fin.mesh.is_watertight
    assert fin.final["min_angle_deg"] >= 20.0
    assert fin.final["nonmanifold_edges"] == 0 and fin.final["boundary_edges"] == 0
    # the volume is the raw's (the whole finishing: measured -0.30 % and +0.03 %; the fins are a few voxels thin).
    # Since the sliver cut keeps the smallest cut that reaches the angle when none also stays within a voxel (seed 0
    # at 2 mm: a cut of 0.7 mm, 22.0 degrees, instead of one of 3 mm at 4.4 degrees that the last step happened to
    # mend): -0.69 % and +0.03 %, the last step's 1.21 -> 0.67 voxel (was 3.46 -> 0.84)
    assert abs(fin.volume_change_pct) < 1.0, fin.volume_change_pct


# Fins thinner than a voxel at 1 mm (0.7 and 0.8 voxel thick): the occupancy is a one-voxel layer whose voxels meet
# diagonally, and on a cube face between two such voxels the bilinear saddle is 0.5, exactly the level.  Lewiner's
# marching cubes resolved the tie one way in one cube and the other way in the next: 63 and 681 edges of four faces.
# Repair then cut those faces out, the holes it could not close sent the surface down the open-surface path, and the
# finished surface was 1.89 / 3.29 voxels off the raw one, 0.79 / 0.10 degrees, not closed, volume -48 % / -68 %.
# Now such a surface is meshed again 1e-5 below the level (TIE_LEVEL), where every tie joins the two voxels.
# Developed on seeds 0-2 (half-thickness 0.25-0.5 voxel); these seeds were not looked at before.  Measured after:
# 0.601 / 0.568 voxel max, 0.128 mean, 21.62 / 21.41 degrees, volume -0.14 % / -0.04 %.  The bounds are the
# promises (1 voxel, 0.25 mean, 20 degrees, closed and manifold) and the volume within 0.5 % (the broken surface
# lost half of it).  Not yet kept: thinner fins, and some of these thicknesses on other seeds (their finished
# surfaces are still up to 2.8 voxels off, with slivers on the fins: the remesher projects a vertex of one side of
# a sheet a fraction of a voxel thick onto the other).
@pytest.mark.parametrize("seed, half", [(6, 0.35), (5, 0.4)])
def test_fins_thinner_than_a_voxel_at_1mm(seed, half):
    from skimage.measure import marching_cubes

    from organlab.surface import mesh_quality

    body, grid = _finned_occupancy(1.0, seed, half)
    raw = mesh_from_field(body, grid)
    # the case is real: at the level itself, marching cubes gives edges of more than two faces
    _, f, _, _ = marching_cubes(np.pad(body.astype(np.float32), 1), 0.5)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    assert (np.unique(e, axis=0, return_counts=True)[1] > 2).sum() > 50
    q = mesh_quality(raw)  # the surface used is closed and manifold
    assert q["nonmanifold_edges"] == q["boundary_edges"] == q["nonmanifold_vertices"] == 0
    fin = finish_surface(raw, voxel_size=1.0)
    dev = surface_deviation(fin.mesh, raw, voxel_size=1.0)
    assert dev["max_voxels"] < 1.0 and dev["mean_voxels"] < 0.25, dev
    assert fin.watertight and fin.final["min_angle_deg"] >= 20.0
    assert fin.final["nonmanifold_edges"] == 0 and fin.final["boundary_edges"] == 0
    assert abs(fin.volume_change_pct) < 0.5, fin.volume_change_pct


def test_within_a_voxel_already_is_left_alone():
    """A plain ball (1.5 mm voxels) is within a voxel after remeshing: no last step, the same surface."""
    grid = VoxelGrid(origin=(-24.0,) * 3, voxel_size=1.5, shape=(33, 33, 33))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    fin = finish_surface(mesh_from_field(x**2 + y**2 + z**2 <= 20.0**2, grid), voxel_size=1.5)
    assert fin.deviation["max_voxels"] < 1.0
    assert not [s for s in fin.steps if s["step"] == "stay_on_data"]


# ------------------------------------------------------------------ sub-voxel walls over tunnels (the slivers' cut)
# What made the 0.25 mm sample's finished surface 1.29 voxels off (benchmarks/bench_finish.py): a 0.5 mm tunnel under a
# wall 0.08-0.2 mm thin, with a 0.1 mm pocket in it, where the remesher's clean-up left four faces below 20 degrees;
# the faces within one target edge of them (0.69 mm = 2.8 voxels) were cut out and filled over the tunnel, 2.1 voxels
# off, and the last step brought back what it could.  Now the cut is the smallest (from the remesher's smallest edge)
# whose result keeps the angle within a voxel of the raw surface.  The scene below was not used to choose that rule:
# a ball with void tubes 0.6-1.6 voxels across under skins 0.05-0.35 voxel thick, each with a pocket in the skin, at
# the sample's 0.25 mm proportions (target edge 3 voxels: 1 mm voxels, min_edge_mm=3).

def _tunnels(seed):
    """A 10 mm ball (1 mm voxels) with four void tubes 6 mm long just under its surface and a pocket in each skin."""
    grid = VoxelGrid(origin=(-14.0,) * 3, voxel_size=1.0, shape=(29, 29, 29))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    rng = np.random.default_rng(seed)
    d = np.sqrt(x**2 + y**2 + z**2) - 10.0
    for _ in range(4):
        a = rng.normal(size=3)
        a /= np.linalg.norm(a)
        u = np.cross(a, rng.normal(size=3))
        u /= np.linalg.norm(u)
        r, skin = rng.uniform(0.3, 0.8), rng.uniform(0.05, 0.35)
        c = (10.0 - r - skin) * a
        p = np.stack([x - c[0], y - c[1], z - c[2]], -1)
        s = p @ u
        d = np.maximum(d, np.minimum(r - np.sqrt(np.maximum((p**2).sum(-1) - s**2, 0.0)), 3.0 - np.abs(s)))
        q = (10.0 - 0.5 * skin) * a + rng.uniform(-2.0, 2.0) * u
        d = np.maximum(d, rng.uniform(0.15, 0.35) - np.sqrt((x - q[0]) ** 2 + (y - q[1]) ** 2 + (z - q[2]) ** 2))
    return mesh_from_field(np.clip(0.5 - d, 0.0, 1.0).astype(np.float32), grid)


# measured (seeds 2 and 4, the two of 0-11 where the remesher leaves faces below the angle): before, the cut of one
# target edge (3 mm) filled the tunnels: 1.53 and 1.48 voxels off, +1.42 % and +1.40 % volume, the last step then
# 0.65 / 0.67 voxel; now cuts of 0.35 mm (64 and 49 faces): 0.55 / 0.52 voxel, volume +0.000 %, 25.6 / 22.0 degrees,
# no last step.  The bounds: under the promised voxel with a margin (0.8), the volume within 0.05 % (a filled tunnel
# is 1.4 %)
# Since ._bandmesh.untie, seed 2's raw surface (its ball's samples at exactly 10 mm, 0.5, had left coincident
# vertices) gives the remesher no face below the angle; seed 17 (of 0-23, the only other where it does) instead:
# 40 faces cut at 0.35 mm, 0.77 voxel, volume +0.0001 %, 21.6 degrees.
@pytest.mark.parametrize("seed", [4, 17])
def test_a_thin_wall_over_a_tunnel_is_not_cut_away(seed, monkeypatch):
    # the cut on the case it was made for, the thin-part handling switched off (as above: with it, no face is left
    # below the angle for the cut, test_thin_parts_are_not_smoothed_through)
    _without_thin(monkeypatch)
    raw = _tunnels(seed)
    fin = finish_surface(raw, voxel_size=1.0, min_edge_mm=3.0)
    cut = [s for s in fin.steps if s["step"] == "slivers"]
    # the case is real: the remesher's clean-up left faces below the angle, and a cut smaller than the edge fixed them
    assert len(cut) == 1 and 0 < cut[0]["faces_cut"] and cut[0]["cut_radius_mm"] < 3.0, fin.steps
    assert fin.watertight and fin.final["min_angle_deg"] >= 20.0
    dev = surface_deviation(fin.mesh, raw, voxel_size=1.0)
    assert dev["max_voxels"] < 0.8 and dev["mean_voxels"] < 0.1, dev
    assert abs(fin.volume_change_pct) < 0.05, fin.volume_change_pct


def test_the_sliver_cut_keeps_the_pieces_it_does_not_touch():
    """cut_and_fill repairs the pieces its cut touches only: a small separate piece elsewhere is no speck of the cut's
    (the 1 mm dino: a piece 57 mm from the cut, under speck_mm after remeshing, was dropped, 3.1 voxels of raw lost)."""
    from organlab.surface._repair import cut_and_fill

    grid = VoxelGrid(origin=(-12.0,) * 3, voxel_size=1.0, shape=(25, 25, 25))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    d = np.minimum(np.sqrt(x**2 + y**2 + z**2) - 7.0, np.sqrt((x - 10.0) ** 2 + y**2 + z**2) - 0.8)
    two = mesh_from_field(np.clip(0.5 - d, 0.0, 1.0).astype(np.float32), grid)  # a ball and a bead 1.6 mm across
    bead = two.vertices[:, 0] > 8.5
    assert 0 < bead.sum() < len(two.vertices) and np.linalg.norm(np.ptp(two.vertices[bead], axis=0)) < 3.0
    out, n = cut_and_fill(two, np.array([[-7.0, 0.0, 0.0]]), 1.5, speck_mm=3.0)  # a cut on the far side of the ball
    assert n > 0 and out.is_watertight
    kept = out.vertices[:, 0] > 8.5
    # the bead is all there, untouched (before: dropped with the cut's repair, 0 of its 6 vertices kept)
    np.testing.assert_array_equal(np.sort(out.vertices[kept], axis=0), np.sort(two.vertices[bead], axis=0))
    # and the cut was filled: the volume within 1 % (measured -0.26 %, the fill a chord across the curved ball)
    assert abs(out.volume - two.volume) / two.volume < 0.01


def test_marching_cubes_joins_voxels_that_meet_at_an_edge():
    """Four voxels that meet at edges only (the smallest piece of a slanted one-voxel fin, seed 5, with such
    edges): their cube faces' saddles are the level; the surface is closed, manifold and one piece (the ties taken
    as joined), on the dense and the band path; a surface without such a tie is scikit-image's at the level."""
    from skimage.measure import marching_cubes

    from organlab.surface import mesh_quality
    from tests.test_surface_scale import _band

    grid = VoxelGrid(origin=(0.0, 0.0, 0.0), voxel_size=1.0, shape=(6, 6, 6))
    occ = np.zeros(grid.shape, dtype=bool)
    occ[tuple(np.array([[1, 1, 1], [1, 2, 2], [2, 0, 1], [2, 1, 2]]).T + 1)] = True
    _, f, _, _ = marching_cubes(np.pad(occ.astype(np.float32), 1), 0.5)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    assert (np.unique(e, axis=0, return_counts=True)[1] > 2).any()  # the case is real
    for field in (occ, _band(occ.astype(np.float32), grid, block=4)[0]):
        m = mesh_from_field(field, grid)
        q = mesh_quality(m)
        assert q["nonmanifold_edges"] == q["boundary_edges"] == q["nonmanifold_vertices"] == 0, q
        assert q["components"] == 1 and m.is_watertight
        assert np.abs(m.vertices - np.round(m.vertices * 2) / 2).max() < 2e-5  # on the edge midpoints, 1e-5 off
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    ball = (x - 2.5) ** 2 + (y - 2.5) ** 2 + (z - 2.5) ** 2 <= 2.2**2
    v, f, _, _ = marching_cubes(np.pad(ball.astype(np.float32), 1), 0.5)
    m = mesh_from_field(ball, grid)
    np.testing.assert_array_equal(m.vertices, v.astype(np.float64) - 1.0)
    assert {tuple(sorted(t)) for t in m.faces.tolist()} == {tuple(sorted(t)) for t in f.tolist()}


# ------------------------------------------------------------------ thin parts are not smoothed through (._thin)
# Taubin smoothing moves each side of a sheet on its own; where a part is thinner than the staircase it relaxes, the
# sides pass through each other, the remesher (starting from the smoothed surface, projecting by closest point)
# puts vertices on the wrong side of the fin, and slivers are left that the later steps cut out or pull back.  Now
# such vertices (and two rings around) get their raw places back before remeshing, and a projection onto the other
# side of a thin part is refused.  Developed on the 1 mm finned balls (occupancy seeds 3, 4, 6; coverage fields);
# the scenes of the two tests above were not used: they now meet the promises with neither the last step nor the
# cut.  Measured against the raw surface less its specks (before, without the later steps' work as their tests
# switch it off -> now): fins 2 mm seed 0: 3.46 voxels -> 0.559 max / 0.090 mean, 23.7 deg; 1.5 mm seed 1: 1.02 ->
# 0.695 / 0.134, 27.0 deg; tunnels seed 2: faces below 20 deg left for the cut -> 0.382 / 0.030, 28.3 deg; 1 mm fins
# 0.8 voxel thick (occupancy seed 4; finished before with every step: 2.80 voxels, 7.75 deg) -> 0.60 / 0.095, 21.3 deg.
# Bounds: the promises, with no later step needed (one would hide a regression here); the volume within 0.15 %
# (measured 0.10 % at most).
@pytest.mark.parametrize("scene", ["fins2", "fins15", "tunnels2", "fins1"])
def test_thin_parts_are_not_smoothed_through(scene):
    raw, vs, kw = {"fins2": lambda: (_finned_ball(2.0, 0), 2.0, {}), "fins15": lambda: (_finned_ball(1.5, 1), 1.5, {}),
                   "tunnels2": lambda: (_tunnels(2), 1.0, {"min_edge_mm": 3.0}),
                   "fins1": lambda: (_finned_ball(1.0, 4, 0.4), 1.0, {})}[scene]()
    from organlab.surface._repair import repair_mesh

    fin = finish_surface(raw, voxel_size=vs, **kw)
    raw, _ = repair_mesh(raw, speck_mm=3.0 * vs)  # the raw surface less its specks, as the promise is stated
    names = [s["step"] for s in fin.steps]
    assert "thin" in names and "stay_on_data" not in names and "slivers" not in names, names
    assert fin.steps[names.index("thin")]["vertices_kept"] > 0
    dev = surface_deviation(fin.mesh, raw, voxel_size=vs)
    assert dev["max_voxels"] < 1.0 and dev["mean_voxels"] < 0.25, dev
    assert fin.watertight and fin.final["min_angle_deg"] >= 20.0
    assert abs(fin.volume_change_pct) < 0.15, fin.volume_change_pct


def test_a_surface_without_thin_parts_is_not_touched():
    """A ball (1 mm, a coverage field): smoothing takes no vertex through anything; no thin step, and
    :func:`._thin.keep_thin` returns the smoothed surface itself."""
    from organlab.surface._repair import smooth_mesh
    from organlab.surface._thin import keep_thin

    field, grid = _field("ball")
    raw = mesh_from_field(field, grid)
    fin = finish_surface(raw, voxel_size=1.0)
    assert "thin" not in [s["step"] for s in fin.steps]
    sm, _ = smooth_mesh(raw)
    assert keep_thin(sm, raw) == (sm, 0)


def test_a_cut_that_takes_whole_pieces_is_refused():
    """cut_and_fill whose cut removes every face of the pieces it touches has nothing to fill: the mesh comes back
    unchanged with 0 faces cut (before 9448c49 repair_mesh raised 'the mesh has no faces' on the empty rest; the
    1 mm finned balls' shreds, seed 2 at 0.3 voxel half-thickness, did this inside finish_surface)."""
    from organlab.surface._repair import cut_and_fill

    grid = VoxelGrid(origin=(-12.0,) * 3, voxel_size=1.0, shape=(25, 25, 25))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    d = np.minimum(np.sqrt(x**2 + y**2 + z**2) - 7.0, np.sqrt((x - 10.0) ** 2 + y**2 + z**2) - 0.8)
    two = mesh_from_field(np.clip(0.5 - d, 0.0, 1.0).astype(np.float32), grid)
    out, n = cut_and_fill(two, np.array([[10.0, 0.0, 0.0]]), 2.5, speck_mm=3.0)  # the whole bead is in the cut
    assert n == 0 and out is two
