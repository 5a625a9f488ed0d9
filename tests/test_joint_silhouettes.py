"""The joint silhouette step (organlab.silhouette.SilhouetteModel.joint): every view against the others' hull.

Exact renders (no noise) of a specimen the defaults were not tuned on (AAA shape seed 7, 12 views of
240 x 180), their true masks (coverage >= 0.5): a correct silhouette is not grown; a part cut out of one
view comes back; a blob no other view explains is dropped; the engine reports what changed.
"""

import numpy as np
import pytest

from organlab.masks import Silhouette
from organlab.silhouette import SilhouetteModel
from organlab.synthetic import default_camera, render_masks, render_view

N_VIEWS, SIZE, SPEC = 12, (240, 180), "aaa-7"
BOX = ((-70.0, -70.0, 0.0), (70.0, 70.0, 200.0))


@pytest.fixture(scope="module")
def scene():
    cam0 = default_camera(SIZE)
    cams = [cam0.at_table_angle(360.0 * i / N_VIEWS) for i in range(N_VIEWS)]
    # images and masks from the same 4 x 4 samples per pixel: the masks are the images' exact silhouettes
    images = [render_view(SPEC, c, supersample=4) for c in cams]
    empty = render_view(None, cams[0], supersample=4)
    cover = render_masks(SPEC, cams, supersample=4)
    return cams, images, empty, cover


def _sils(model, masks):
    return [Silhouette(m, model._coverage(i, m), 10.0, "subtraction") for i, m in enumerate(masks)]


KEYINGS = [None, {"color": "frames"}]


@pytest.mark.parametrize("backdrop", KEYINGS, ids=["subtraction", "keyed"])
def test_a_correct_silhouette_is_not_grown(scene, backdrop):
    cams, images, empty, cover = scene
    model = SilhouetteModel(images, [empty], backdrop=backdrop)
    true = [c >= 0.5 for c in cover]
    out, summary = model.joint(_sils(model, true), cams, BOX)
    added = [v["added"] for v in summary["views"]]
    removed = [v["removed"] for v in summary["views"]]
    # measured: 0 px added and 0 removed in every view (the prior's slack beyond the outline is refused by
    # the regions' erosion, the edge pixels covered by half or less by the edge rule, 0.6 of the contrast around; at 0.5 it
    # added 1-2 px per view covered 0.38-0.44, the texture's and the shading's spread over the window)
    assert max(added) == 0 and max(removed) == 0, (added, removed)
    for s, t in zip(out, true):
        assert np.array_equal(s.mask, t)
        assert s.info["joint"] == {"added": 0, "removed": 0}


@pytest.mark.parametrize("backdrop", KEYINGS, ids=["subtraction", "keyed"])
def test_a_part_one_view_lost_comes_back_and_a_blob_no_view_explains_goes(scene, backdrop):
    """Keyed views (Delta E against the backdrop) get neither the edge rule nor the region rule: the notch comes back
    by the required rule (the voxels only view 3 carves, on pixels other views cannot explain without them)."""
    cams, images, empty, cover = scene
    model = SilhouetteModel(images, [empty], backdrop=backdrop)
    true = [c >= 0.5 for c in cover]
    masks = [t.copy() for t in true]
    # view 3 loses a notch on its outline (as a dark part below the threshold would)
    ys, xs = np.nonzero(true[3])
    cy, cx = int(np.median(ys)), int(xs.max()) - 2
    yy, xx = np.mgrid[: true[3].shape[0], : true[3].shape[1]]
    notch = ((yy - cy) ** 2 + (xx - cx) ** 2 <= 6**2) & true[3]
    masks[3] &= ~notch
    # view 5 gains a blob on the backdrop far from the specimen (a shadow, a speck), attached to nothing
    blob = (yy - 20) ** 2 + (xx - 30) ** 2 <= 4**2
    assert not (blob & true[5]).any()
    masks[5] |= blob
    out, summary = model.joint(_sils(model, masks), cams, BOX)
    back = np.count_nonzero(out[3].mask & notch) / np.count_nonzero(notch)
    # measured: the whole notch (1.00) comes back by subtraction (edge and region rules), 0.78 keyed (the required
    # rule alone: the notch's outermost pixels graze the outline, where the other views' rays are explained within the
    # prior's 1.5 px voxels, so nothing requires them); no pixel outside the true mask is added; the blob goes
    assert back >= (0.7 if backdrop else 0.9), back
    assert not (out[3].mask & ~true[3]).any()
    assert not (out[5].mask & blob).any()
    assert summary["views"][3]["added"] >= (0.7 if backdrop else 0.9) * np.count_nonzero(notch)
    assert summary["views"][5]["removed"] == np.count_nonzero(blob)
    # the views that were right are unchanged
    for i in (0, 1, 2, 4, 6, 7, 8, 9, 10, 11):
        assert np.array_equal(out[i].mask, true[i]), i


def test_given_masks_are_kept_and_bad_arguments_are_refused(scene):
    cams, images, empty, cover = scene
    true = [c >= 0.5 for c in cover]
    masks = [None] * N_VIEWS
    masks[3] = true[3] & ~np.eye(*true[3].shape, dtype=bool)  # a given mask is used as it is
    model = SilhouetteModel([None if m is not None else im for im, m in zip(images, masks)], [empty], masks=masks)
    sils = _sils_given(model, true, masks)
    out, _ = model.joint(sils, cams, BOX)
    assert np.array_equal(out[3].mask, masks[3])
    with pytest.raises(ValueError, match="silhouettes"):
        model.joint(sils[:-1], cams, BOX)


def _sils_given(model, true, masks):
    return [Silhouette(m, m.astype(np.float32), None, "given") if m is not None
            else Silhouette(t, model._coverage(i, t), 10.0, "subtraction") for i, (t, m) in enumerate(zip(true, masks))]


def test_engine_setting_and_report(tmp_path):
    """Settings.joint_silhouettes validates; the report says whether the step ran and what it changed per view."""
    from organlab.engine import Engine, Settings
    from organlab.errors import SettingsError
    from tests._shared_data import copy_sample

    with pytest.raises(SettingsError, match="joint_silhouettes"):
        Settings(joint_silhouettes="yes").validate()
    root = copy_sample(tmp_path / "s", calibration=True, views=3)  # 12 views of background subtraction
    eng = Engine(root)
    assert Settings().joint_silhouettes == "auto"  # the default: keyed sessions only (docs/silhouettes.md says why)
    assert not eng.silhouette_model.joint_applies()  # 'auto' leaves a subtraction session alone
    rec = eng.run(Settings(voxel_size=4.0, finish=False, measure=False, joint_silhouettes="on"))
    j = rec.report["joint_silhouettes"]
    assert j["mode"] == "on" and j["ran"] and j["iterations"] >= 1
    rows = [v["silhouette_joint"] for v in rec.report["views"]]
    assert j["added_px"] == sum(r["added"] for r in rows) and j["removed_px"] == sum(r["removed"] for r in rows)
    # the sample's silhouettes are right: measured 59 px added in all (58 in one view: a region between the
    # legs that these 12 views' hull fills, its shading away from the backdrop's), 0 removed; 36 views at 1 mm:
    # 4 px in all, volume -0.213 % either way; 12 views at 1 mm: +1.390 % -> +1.400 %
    assert sum(r["added"] + r["removed"] for r in rows) <= 150
    off = eng.run(Settings(voxel_size=4.0, finish=False, measure=False, joint_silhouettes="off"))
    assert off.report["joint_silhouettes"] == {"mode": "off", "ran": False}
    assert "silhouette_joint" not in off.report["views"][0]
    assert abs(off.report["volume_mm3"] - rec.report["volume_mm3"]) <= 1e-3 * off.report["volume_mm3"]


def test_the_prior_projects_as_model_mask_projects_it(scene):
    """The joint step finds the prior hull's boundary faces once a round and fills them in every view
    (raster.MeshRaster): the same pixels as raster.model_mask of the occupancy, which finds them per view."""
    from organlab.raster import MeshRaster, model_mask, voxel_boundary_quads
    from organlab.silhouette._joint import prior_hull

    cams, _, _, cover = scene
    masks = [c >= 0.5 for c in cover]
    masks[3] = masks[3] & ~np.roll(masks[3], 7, axis=1)  # one view with a strip cut: the tolerant hull keeps it
    grid, hull = prior_hull(masks, cams, BOX)
    assert hull.sum() > 1000
    raster = MeshRaster(*voxel_boundary_quads(hull, grid))
    for cam, m in zip(cams, masks):
        got = raster.mask(cam, m.shape)
        assert got.sum() > 0.5 * m.sum()
        np.testing.assert_array_equal(got, model_mask(hull, cam, grid=grid))
