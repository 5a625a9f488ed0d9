"""The engine: typed settings, stages kept across runs, invalidation, streaming, cancel, until."""

import numpy as np
import pytest

from organlab.engine import DEPENDS, STAGES, Cancelled, Engine, Settings, SettingsError, run
from organlab.errors import OrganlabError
from organlab.pipeline import reconstruct
from organlab.synthetic import make_session


@pytest.fixture(scope="module")
def posed(tmp_path_factory):
    """A small session the defaults were not tuned on (seed 11, 10 views of 320 x 240), cameras given."""
    root = tmp_path_factory.mktemp("engine") / "s"
    truth = make_session(root, image_size=(320, 240), n_views=10, n_background=4, views_only=True, seed=11)
    return root, truth


def test_settings_validate_naming_the_parameter():
    s = Settings(voxel_size=2.0, threshold=20.0, roi=((-10, -10, 0), (10, 10, 30)))
    assert Settings.from_dict(s.to_dict()) == s
    assert s.replace(threshold=None).threshold is None and s.threshold == 20.0  # a copy, not changed in place
    for bad, name in [(dict(threshold=-1), "threshold"), (dict(voxel_size=float("nan")), "voxel_size"),
                      (dict(method="nope"), "method"), (dict(hull="x"), "hull"), (dict(tolerance=1.5), "tolerance"),
                      (dict(color_threshold=0), "color_threshold"), (dict(roi=((0, 0, 0), (1, 1, -1))), "roi"),
                      (dict(measure="yes"), "measure")]:
        with pytest.raises(SettingsError) as e:
            Settings(**bad).validate()
        assert e.value.parameter == name and str(e.value).startswith(f"{name} must") and "--" not in str(e.value)
    with pytest.raises(SettingsError, match="colour_threshold is not a setting"):
        Settings.from_dict({"colour_threshold": 3})
    with pytest.raises(SettingsError, match="^threshold must"):  # from Python: the parameter, not the CLI flag
        reconstruct("sample_sessions/aaa_phantom", threshold=-1)


def test_stages_and_their_settings():
    assert STAGES[0] == "calibration" and STAGES[-1] == "checks"
    assert STAGES.index("silhouettes") < STAGES.index("carving") < STAGES.index("coloring") < STAGES.index("surface")
    fields = {f for deps in DEPENDS.values() for f in deps}
    assert fields == set(Settings.__dataclass_fields__)  # every setting invalidates some stage


def test_engine_reruns_only_what_a_setting_invalidates(posed):
    root, truth = posed
    eng = Engine(root)
    seen = []
    base = Settings(voxel_size=2.0, finish=False)
    rec = eng.run(base, on_stage=lambda name, result: seen.append(name))
    assert seen == ["calibration", "silhouettes", "carving", "coloring", "mesh", "surface", "checks"]
    assert all(eng.computed[s] == 1 for s in STAGES)
    # the same result as reconstruct()
    ref = reconstruct(root, voxel_size=2.0, finish=False)
    np.testing.assert_array_equal(rec.occupancy, ref.occupancy)
    np.testing.assert_array_equal(rec.mesh.vertices, ref.mesh.vertices)
    assert rec.report["mesh_volume_mm3"] == ref.report["mesh_volume_mm3"]

    # a new threshold: silhouettes onward, never calibration
    t = eng.run(base.replace(threshold=30.0))
    assert eng.computed["calibration"] == 1 and eng.computed["silhouettes"] == 2 and eng.computed["checks"] == 2
    assert t.silhouettes[0].threshold == 30.0 and t.occupancy.sum() != rec.occupancy.sum()
    # a new voxel size: calibration and silhouettes kept
    v = eng.run(base.replace(threshold=30.0, voxel_size=4.0))
    assert eng.computed["silhouettes"] == 2 and eng.computed["carving"] == 2 + 1
    assert v.silhouettes is t.silhouettes and v.grid.voxel_size == 4.0
    # only the surface's setting: carving kept
    f = eng.run(base.replace(threshold=30.0, voxel_size=4.0, finish=True))
    assert eng.computed["carving"] == 3 and eng.computed["surface"] == 4
    assert f.report["surface"]["final"]["faces"] == len(f.mesh.faces)
    # back to the first settings: one entry kept per stage, so silhouettes onward run again (calibration kept)
    before = dict(eng.computed)
    again = eng.run(base)
    assert eng.computed == {k: v + (k != "calibration") for k, v in before.items()}
    # the same settings again: nothing recomputed, the same figures
    after = dict(eng.computed)
    again2 = eng.run(base)
    assert eng.computed == after and again2.report["mesh_volume_mm3"] == again.report["mesh_volume_mm3"]
    assert again.report["mesh_volume_mm3"] == rec.report["mesh_volume_mm3"]


def test_until_and_cancel(posed):
    root, _ = posed
    eng = Engine(root, views=[0, 2, 4, 6, 8])
    rec = eng.run(Settings(voxel_size=3.0), until="carving")
    assert rec.occupancy.any() and rec.mesh is None and rec.report is None and len(rec.cameras) == 5
    with pytest.raises(SettingsError, match="until must be one of"):
        eng.run(Settings(), until="meshing")
    calls = []

    def cancel():
        calls.append(1)
        return len(calls) > 3  # cancelled during the carving

    with pytest.raises(Cancelled):
        eng.run(Settings(voxel_size=2.0), cancel=cancel)
    assert eng.computed["carving"] == 1  # the cancelled carving was not kept
    full = eng.run(Settings(voxel_size=3.0))  # the kept carving reused; the views' rows are those of views 0, 2, ...
    assert eng.computed["carving"] == 1 and [r["image"] for r in full.report["views"]] == eng.names
    assert full.views == [0, 2, 4, 6, 8]


def test_run_and_save_load(posed, tmp_path):
    root, truth = posed
    rec = run(root, Settings(voxel_size=2.0))
    # 10 views of 320 x 240 at 2 mm: within 2 % of the phantom (measured -0.3 %)
    assert rec.mesh.volume == pytest.approx(truth["volume_mm3"], rel=0.02)
    paths = rec.save(tmp_path / "out")
    assert {p.name for p in paths.values()} == {"report.json", "voxels.npz", "mesh.ply", "mesh.stl"}
    back = type(rec).load(tmp_path / "out")
    np.testing.assert_array_equal(back.occupancy, rec.occupancy)
    np.testing.assert_allclose(np.asarray(back.field), np.asarray(rec.field))
    assert back.mesh.volume == pytest.approx(rec.mesh.volume, rel=1e-6)
    assert back.report["mesh_volume_mm3"] == rec.report["mesh_volume_mm3"] and back.settings.voxel_size == 2.0
    assert back.agreement == rec.agreement  # the same figures and ranking, read from report.json
    with pytest.raises(OrganlabError, match="mesh.ply: missing"):
        (tmp_path / "out" / "mesh.ply").unlink()
        type(rec).load(tmp_path / "out")
