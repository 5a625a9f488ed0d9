"""Issue 26, item 7: the viewer bounds every control on the server (viser does not enforce a slider's
limits) and runs the grid memory pre-flight before each re-run.  A crafted message set a 0.05 mm voxel
or a 3 m roi and kept the worker busy for 30-45 s at 2.8 GB."""

import pytest
from _hostile import small_calibrated

pytest.importorskip("viser")


@pytest.fixture(scope="module")
def viewer(tmp_path_factory):
    from organlab.viewer import SessionViewer

    v = SessionViewer(small_calibrated(tmp_path_factory), voxel_size=4.0, port=0)
    yield v
    v.stop()


@pytest.fixture
def calls(viewer, monkeypatch):
    out = []
    monkeypatch.setattr(viewer, "rerun", lambda **changes: out.append(changes))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("name, crafted, bounded", [
    ("voxel", 0.05, 0.5), ("voxel", float("nan"), 0.5), ("voxel", 1e9, 5.0),
    ("threshold", -3.0, 1.0), ("tolerance", 99, 5), ("tolerance", -1, 0),
])
def test_crafted_slider_values_are_bounded_on_the_server(viewer, calls, name, crafted, bounded):
    c = viewer.controls
    handle = getattr(c, name)
    handle.value = crafted  # as a crafted client message would set it: on_update runs
    assert handle.value == bounded
    key = {"voxel": "voxel_size", "threshold": "threshold", "tolerance": "tolerance"}[name]
    assert calls and calls[-1][key] == bounded, calls


@pytest.mark.slow
def test_crafted_roi_and_choices_are_bounded_and_preflighted(viewer, calls):
    c = viewer.controls
    c.roi_size.value = (3000.0, 3000.0, float("inf"))
    assert tuple(c.roi_size.value) == (1000.0, 1000.0, 1.0)
    c.method.value = "rm -rf"
    assert c.method.value == "hull"
    # a 1 m cube at 0.5 mm: 8e9 voxels, about 300 GiB: refused before the worker starts
    c.voxel.value = 0.5
    calls.clear()
    c.roi_size.value = (1000.0, 1000.0, 1000.0)
    c._settings_changed(roi=c.roi())
    assert calls == [] and "not run" in c.status.content and "needs about" in c.status.content
