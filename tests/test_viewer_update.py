"""The viewer's full update (issue 24): the engine carves beside the poses stage, and keeps that carving only
when the poses stage kept the cameras; the viewer sends hidden voxels after the full update."""

import dataclasses

import numpy as np
import pytest

import organlab.engine as engine_module
from organlab.engine import Engine, Settings
from organlab.synthetic import make_session


@pytest.fixture(scope="module")
def posed(tmp_path_factory):
    """A small session the defaults were not tuned on (seed 23, 12 views of 320 x 240), cameras given."""
    root = tmp_path_factory.mktemp("update") / "s"
    make_session(root, image_size=(320, 240), n_views=12, n_background=4, views_only=True, seed=23)
    return root


def _run(root, beside, monkeypatch, settings):
    monkeypatch.setattr(engine_module, "_CARVE_BESIDE_POSES", beside)
    eng = Engine(root)
    threads = []
    real = engine_module.refine_poses

    def refine(*a, **k):  # which thread ran the poses stage
        import threading

        threads.append(threading.current_thread().name)
        return real(*a, **k)

    monkeypatch.setattr(engine_module, "refine_poses", refine)
    rec = eng.run(settings, until="carving")
    monkeypatch.setattr(engine_module, "refine_poses", real)
    return eng, rec, threads


def test_carving_beside_the_poses_stage_is_the_carving_after_it(posed, monkeypatch):
    st = Settings(voxel_size=3.0, finish=False)
    seq, a, t_seq = _run(posed, False, monkeypatch, st)
    par, b, t_par = _run(posed, True, monkeypatch, st)
    assert t_seq == ["MainThread"] and t_par[0].startswith("organlab-poses")  # it did run beside the carving
    np.testing.assert_array_equal(a.occupancy, b.occupancy)
    np.testing.assert_array_equal(a.field.values, b.field.values)  # the sub-voxel field too (BandField)
    np.testing.assert_array_equal(a.field.states, b.field.states)
    assert seq.computed == par.computed  # each stage once, both ways: the carving beside it was kept
    assert par.cached("poses", st) and par.cached("carving", st)
    # the next run with the same settings recomputes nothing; a new threshold re-runs both, beside again
    par.run(st, until="carving")
    assert par.computed["poses"] == par.computed["carving"] == 1
    par.run(st.replace(threshold=25.0), until="carving")
    assert par.computed["poses"] == par.computed["carving"] == 2


def test_carving_redone_when_the_poses_stage_corrects_the_cameras(posed, monkeypatch):
    """A poses stage that moves the cameras (here by hand: every camera 4 mm along x) must carve with them."""
    real = engine_module.refine_poses

    def moved(*a, **k):
        r = real(*a, **k)
        cams = [dataclasses.replace(c, t=np.asarray(c.t, float) + c.R @ np.array([4.0, 0.0, 0.0])) for c in r.cameras]
        return dataclasses.replace(r, cameras=cams, accepted=True)

    st = Settings(voxel_size=3.0, finish=False)
    results = {}
    for beside in (False, True):
        monkeypatch.setattr(engine_module, "_CARVE_BESIDE_POSES", beside)
        monkeypatch.setattr(engine_module, "refine_poses", moved)
        eng = Engine(posed)
        rec = eng.run(st, until="carving")
        results[beside] = (eng, rec)
    (seq, a), (par, b) = results[False], results[True]
    assert par.computed["carving"] == seq.computed["carving"] == 1  # the one beside the poses was dropped
    np.testing.assert_array_equal(a.occupancy, b.occupancy)
    # and it is the carving of the moved cameras, not of the given ones (the specimen is 4 mm off: fewer voxels)
    monkeypatch.setattr(engine_module, "refine_poses", real)
    given = Engine(posed).run(st, until="carving")
    assert not np.array_equal(given.occupancy, b.occupancy)
    assert b.cameras[0].t[0] != given.cameras[0].t[0]


def test_a_newer_request_does_not_wait_for_the_poses_stage(posed, monkeypatch):
    """Cancelled once the carving is done, while the poses stage still runs: the run stops, the poses thread is
    left to end on its own and nothing of it is kept."""
    import threading

    from organlab.engine import Cancelled

    real_poses, real_carving = engine_module.refine_poses, Engine._run_carving
    release, carved = threading.Event(), threading.Event()

    def blocked(*a, **k):
        assert release.wait(60)  # held until the run has returned
        return real_poses(*a, **k)

    def carving(self, *a, **k):  # the carving done: cancelled from now on (the run waits for the poses stage)
        out = real_carving(self, *a, **k)
        carved.set()
        return out

    monkeypatch.setattr(engine_module, "_CARVE_BESIDE_POSES", True)
    monkeypatch.setattr(engine_module, "refine_poses", blocked)
    monkeypatch.setattr(Engine, "_run_carving", carving)
    eng = Engine(posed)
    st = Settings(voxel_size=3.0, finish=False)
    try:
        with pytest.raises(Cancelled):
            eng.run(st, until="carving", cancel=carved.is_set)
        assert carved.is_set() and not release.is_set()  # it returned while the poses stage was still held
    finally:
        release.set()
    assert not eng.cached("poses", st) and not eng.cached("carving", st)
    assert eng.computed["poses"] == eng.computed["carving"] == 0


def test_big_grids_carve_after_the_poses_stage(posed, monkeypatch):
    """Over _CONCURRENT_MEASURES_VOXELS (here lowered to 1000 voxels) the memory peaks would add up: in turn."""
    monkeypatch.setattr(engine_module, "_CONCURRENT_MEASURES_VOXELS", 1000)
    _, _, threads = _run(posed, True, monkeypatch, Settings(voxel_size=3.0, finish=False))
    assert threads == ["MainThread"]
