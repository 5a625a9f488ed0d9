"""The photo method (issue 22): patch NCC between neighbouring views carves what no silhouette shows.

The scene is one no default was tuned on: :class:`BowlSpecimen` (four
bowl-shaped dents inside every silhouette, multi-scale noise texture) under
the hard lamp (shadows, highlights, +-10 % exposure, JPEG), 18 views, known
cameras, small and fast (480 x 360 px, supersample 1, 2 mm voxels; rendered once for the module).  The 1 mm figures on
both textured specimens (36 views) are in docs/benchmarks.md
(benchmarks/bench_photo.py).
"""

import numpy as np
import pytest
from scipy import ndimage

import organlab as ol
from organlab.carving import hull_field
from organlab.coloring import DEFAULT_PHOTO_THRESHOLD, carved_depth_picture, carved_where, photo_carve, report_entry
from organlab.raster import model_mask
from organlab.synthetic import make_session
from organlab.synthetic._textured import BowlSpecimen, GrooveSaddleSpecimen, photo_albedo
from tests._shared_data import DINO, needs_dino


def _fraction_inside(spec, grid, region, n=3):
    """Fraction of each voxel of ``region`` inside the specimen (n^3 sub-samples)."""
    idx = np.argwhere(region)
    off = ((np.arange(n) + 0.5) / n - 0.5) * grid.voxel_size
    o = np.stack(np.meshgrid(off, off, off, indexing="ij"), -1).reshape(-1, 3)
    p = (np.asarray(grid.origin) + idx * grid.voxel_size)[:, None, :] + o[None]
    out = np.zeros(grid.shape)
    out[tuple(idx.T)] = spec.inside(p.reshape(-1, 3)).reshape(len(idx), -1).mean(1)
    return out


@pytest.fixture(scope="module")
def bowls(tmp_path_factory):
    spec = BowlSpecimen()
    folder = tmp_path_factory.mktemp("photo") / "bowls"
    # 480 x 360: about half the CPU of 640 x 480 for the render and each photo_carve; at 320 x 240 the
    # 2 mm hull's own loss doubles (2.28 %) and only 49.6 % of its excess goes: too coarse for "most"
    make_session(folder, specimen=spec, n_views=18, hard=True, image_size=(480, 360),
                 views_only=True, supersample=1, n_background=6, seed=3)
    s = ol.load_session(folder)
    cal, _ = ol.calibration_for(s)
    cams, grid = cal.cameras(s), ol.VoxelGrid.from_session(s, voxel_size=2.0)
    sils = ol.silhouettes(s)
    masks = [x.mask for x in sils]
    hull = hull_field(sils, cams, grid, sparse=True).occupancy()  # what the engine colours
    images = [s.read(v.image) for v in s.views]
    frac = _fraction_inside(spec, grid, ndimage.binary_dilation(hull, iterations=2))
    return folder, spec, cams, grid, masks, hull, images, frac


def _excess_lost(occ, frac, spec, grid):
    h3 = grid.voxel_size**3
    return 100 * (1 - frac)[occ].sum() * h3 / spec.volume, 100 * frac[~occ].sum() * h3 / spec.volume


def test_specimens_exact_volume_and_texture():
    """Quadrature volumes against Monte Carlo; the texture varies at several scales and in colour."""
    rng = np.random.default_rng(0)
    for spec in (BowlSpecimen(), GrooveSaddleSpecimen()):
        lo, hi = spec.bounds
        p = lo + rng.random((100_000, 3)) * (hi - lo)
        mc = spec.inside(p).mean() * np.prod(hi - lo)
        assert abs(mc / spec.volume - 1) < 0.015  # Monte Carlo standard error about 0.3 %
        assert spec.volume < np.pi * spec.star.r_max**2 * (hi[2] - lo[2])
    line = np.stack([np.zeros(400), np.full(400, 35.0), np.linspace(10, 70, 400)], 1)
    a = photo_albedo(line)
    g = a.mean(1)
    assert g.std() > 15  # measured about 30 grey levels: high contrast
    assert np.abs(np.diff(g)).mean() > 0.3  # fine detail at 0.15 mm steps (not only smooth blotches)
    assert np.ptp(a[:, 1] - a[:, 0]) > 20  # colour varies, not only brightness


def test_photo_carves_the_hidden_bowls(bowls):
    """Most of the hull's excess goes, almost nothing of the specimen; no silhouette pixel is lost."""
    folder, spec, cams, grid, masks, hull, images, frac = bowls
    r = photo_carve(images, cams, hull, grid, masks=masks)
    ex0, lost0 = _excess_lost(hull, frac, spec, grid)
    ex, lost = _excess_lost(r.occupancy, frac, spec, grid)
    assert r.method == "photo" and r.threshold == DEFAULT_PHOTO_THRESHOLD
    assert not np.any(r.occupancy & ~hull)
    # measured at 2 mm, 18 views, 480 x 360: hull excess 8.25 %, 54.6 % of it removed; lost 1.53 % -> 1.60 %
    # (the 2 mm hull's own loss is voxel quantisation); 0.5x / 2x of the gain: 54.9 % / 48.5 % removed,
    # 0.09 / 0.02 % lost.  At 640 x 480: 61.9 % removed, 1.24 % -> 1.38 % lost; at 320 x 240: 49.6 %.
    # Before the third pair's confirmation (640 x 480): 63.2 % removed, 0.35 % lost (the bound below would
    # pass it; the sample's test is the one it fails).  Room for noise, not for a regression.
    assert (ex0 - ex) / ex0 > 0.5
    assert lost - lost0 < 0.3
    for c, m in zip(cams, masks):  # the guard: every silhouette pixel the hull explained stays explained
        assert not (m & model_mask(hull, c, grid=grid) & ~model_mask(r.occupancy, c, grid=grid)).any()
    entry = report_entry(r, hull, grid)
    assert entry["method"] == "photo" and entry["removed_volume_mm3"] > 0
    assert sum(x["volume_mm3"] for x in entry["regions"]) <= entry["removed_volume_mm3"] + 1e-6
    # the bowls (9 mm deep at their centres) are among the regions; none deeper than the hull allows (measured 13.4 mm)
    assert 0 < max(x["max_depth_mm"] for x in entry["regions"]) < 30


def test_photo_leaves_the_sample_phantom(tmp_path):
    """The AAA sample: smooth shading and sparse spots, nothing to carve but the roof over its flat top cap.

    Scored against the exact phantom (its constants were never measured on it before this rule): what
    the carving takes of the true volume stays small; the volume stays close to the hull's.
    """
    from organlab.synthetic import with_true_cameras
    from organlab.synthetic._specimens import AAAPhantom

    s = ol.load_session(with_true_cameras("sample_sessions/aaa_phantom", tmp_path / "aaa", step=2))
    cal, _ = ol.calibration_for(s)
    cams, grid = cal.cameras(s), ol.VoxelGrid.from_session(s, voxel_size=2.0)
    sils = ol.silhouettes(s)
    masks = [x.mask for x in sils]
    hull = hull_field(sils, cams, grid, sparse=True).occupancy()
    spec = AAAPhantom()
    frac = _fraction_inside(spec, grid, ndimage.binary_dilation(hull, iterations=2))
    r = photo_carve([s.read(v.image) for v in s.views], cams, hull, grid, masks=masks)
    ex0, lost0 = _excess_lost(hull, frac, spec, grid)
    ex, lost = _excess_lost(r.occupancy, frac, spec, grid)
    # measured (18 views, 2 mm): 0.028 % of the true volume lost by carving; the rule before the third
    # pair's confirmation (with its 1.5-voxel margin) lost 0.102 %
    assert lost - lost0 < 0.07
    carved = hull & ~r.occupancy
    # measured: 29 voxels carved, 0.20 of them inside on average (mostly the roof over the cap: empty space)
    assert carved.any() and frac[carved].mean() < 0.5
    # measured -0.139 % (before: -0.24 %); the roof alone is about 0.35 % of the hull at 1 mm
    assert abs(grid.volume_of(r.occupancy) / grid.volume_of(hull) - 1) < 0.002


def test_photo_threshold_orders_the_carving(bowls):
    """A larger NCC gain asks for more evidence: never more carved."""
    folder, spec, cams, grid, masks, hull, images, frac = bowls
    lo = photo_carve(images, cams, hull, grid, masks=masks, threshold=0.15, passes=1)
    hi = photo_carve(images, cams, hull, grid, masks=masks, threshold=0.6, passes=1)
    assert hi.n_carved <= lo.n_carved  # measured (2 mm, one pass, 480 x 360): 1722 <= 2078 voxels (640 x 480: 2054 <= 2460)
    assert hi.n_carved > 0.5 * lo.n_carved  # no cliff over 4x of the gain


def test_photo_bad_input(bowls):
    folder, spec, cams, grid, masks, hull, images, frac = bowls
    for kw, msg in [({"threshold": 0}, "threshold must be an NCC gain"), ({"window": 4}, "window must be an odd"),
                    ({"min_views": 0}, "min_views must be"), ({"depth": -1}, "depth must be"),
                    ({"passes": 0}, "passes must be")]:
        with pytest.raises(ValueError, match=msg):
            photo_carve(images, cams, hull, grid, masks=masks, **kw)
    with pytest.raises(ValueError, match="occupancy has shape"):
        photo_carve(images, cams, hull[1:], grid, masks=masks)


def test_carved_where_and_picture(tmp_path):
    g = ol.VoxelGrid.from_roi(np.array([-20.0, -20, 0]), np.array([20.0, 20, 40]), 1.0)
    c = g.centers().reshape(g.shape + (3,))
    hull = np.hypot(c[..., 0], c[..., 1]) <= 15
    occ = hull & ~((np.hypot(c[..., 0] - 15, c[..., 1]) <= 5) & (c[..., 2] > 10) & (c[..., 2] < 20))
    w = carved_where(hull, occ, g)
    (reg,) = w["regions"]
    assert abs(reg["centre_mm"][2] - 15) < 1 and reg["centre_mm"][0] > 11  # where the bite is
    assert 4 <= reg["max_depth_mm"] <= 6  # a 5 mm bite below the hull's surface
    m = np.asarray(w["depth_map"]["mm"])
    assert m[0].max() > 4 and m[36].max() == 0  # table angle 0 (the +x side) carved, 180 degrees not
    p = carved_depth_picture(w, tmp_path / "carved.png")
    import cv2

    assert cv2.imread(str(p)).shape[0] > 100


@pytest.mark.slow
def test_engine_offers_photo(bowls, tmp_path):
    """The one engine runs it: report.json says where it carved, voxels.npz holds the carved occupancy."""
    folder = bowls[0]
    rec = ol.reconstruct(folder, voxel_size=2.0, method="photo", finish=False)
    info = rec.report["coloring"]
    assert info["method"] == "photo" and info["removed_volume_mm3"] > 0 and info["regions"]
    ol.write_outputs(rec, tmp_path / "out")
    occ = np.load(tmp_path / "out" / "voxels.npz")["occupancy"]
    assert occ.sum() == rec.occupancy.sum() < bowls[5].sum()


@needs_dino
@pytest.mark.slow
def test_dino_photo_keeps_the_silhouettes():
    """Real photos, the authors' masks, at half size (320 x 240), 2 mm: the photo model's silhouette IoU stays
    within 0.005 of the hull's, and it carves a real part of the hull without hollowing it."""
    import cv2

    from organlab.camera import Camera
    from organlab.datasets import load_middlebury, middlebury_silhouettes

    data = load_middlebury(DINO)
    good = np.nonzero(data.good)[0]
    imgs = [data.images[i] for i in good]
    cams = [data.cameras[i] for i in good]
    masks = middlebury_silhouettes(imgs)  # the authors' recipe on the photos as published (640 x 480)
    # half size: the photos area-averaged, the masks too (kept where half or more of the 4 pixels were in), the
    # cameras' K scaled about the pixel centres.  The sweep's cost is pixels x depth steps (a step moves a point
    # by 0.5 px): an eighth of the full size's.  Measured (CPU, one process, load 7 on 2 cores): full size at 3 mm
    # 50-58 s with 0.75 % of the hull carved and the IoU unchanged (+0.0000); half size at 2 mm 6.2 s, 12.8 % of the
    # hull carved (1 933 voxels; 2 394 put back by the guard), IoU 0.9460 vs the hull's 0.9451 (+0.0008)
    w, h = cams[0].image_size[0] // 2, cams[0].image_size[1] // 2
    half = np.array([[0.5, 0.0, -0.25], [0.0, 0.5, -0.25], [0.0, 0.0, 1.0]])  # (u + 0.5) / 2 - 0.5
    imgs = [cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA) for im in imgs]
    masks = [cv2.resize(m.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) >= 0.5 for m in masks]
    cams = [Camera(half @ c.K, c.dist, c.R, c.t, (w, h)) for c in cams]
    grid = ol.VoxelGrid.from_roi(data.bbox[0] - 4.0, data.bbox[1] + 4.0, 2.0)
    hull = hull_field([m.astype(np.float32) for m in masks], cams, grid) >= 0.5
    r = photo_carve(imgs, cams, hull, grid, masks=masks)

    def iou(occ):
        return np.mean([((m2 := model_mask(occ, c, grid=grid)) & m).sum() / (m2 | m).sum() for c, m in zip(cams, masks)])

    # the guard keeps every silhouette pixel the hull explained, so carving can only tighten the model
    assert iou(r.occupancy) > iou(hull) - 0.005
    # measured at 1 mm on the full-size photos (benchmarks/bench_photo.py dino): IoU 0.9678 vs the hull's 0.9674,
    # 15.6 % of the 16-view hull's volume carved (21 831 voxels put back by the guard); here 12.8 %: not a hollowed
    # model, and not the hull left as it was
    assert 0.75 * grid.volume_of(hull) < grid.volume_of(r.occupancy) < 0.95 * grid.volume_of(hull)
