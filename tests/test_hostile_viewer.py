"""Issue 26, item 7: the viewer bounds every control on the server (viser does not enforce a slider's
limits) and runs the grid memory pre-flight before each re-run.  A crafted message set a 0.05 mm voxel
or a 3 m roi and kept the worker busy for 30-45 s at 2.8 GB."""

import numpy as np
import pytest
from _hostile import small_calibrated

pytest.importorskip("viser")


@pytest.fixture(scope="module")
def viewer(tmp_path_factory):
    from organlab.viewer import SessionViewer

    v = SessionViewer(small_calibrated(tmp_path_factory), voxel_size=4.0, port=0)
    # its first run shown before any crafted value: finishing later (seen once under a load of 15-20) it wrote its
    # own status over the pre-flight's "not run" line
    assert v.wait(timeout=180), v.errors
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


@pytest.mark.slow
def test_crafted_roi_gizmo_position_is_bounded_on_the_server(viewer, calls):
    """The gizmo's translation limits are the browser's; a crafted message may send any position."""
    c = viewer.controls
    c.roi_edit.value = True
    try:
        gizmo = c._roi_gizmo
        limit = 5 * float(np.linalg.norm(c._roi_size()))
        before = np.array(c._roi_centre, float)
        for crafted, want in [((float("nan"), 0.0, 0.0), before), ((1e308, -1e308, 0.0), (limit, -limit, 0.0))]:
            gizmo._impl.wxyz, gizmo._impl.position = np.array([1.0, 0, 0, 0]), np.array(crafted)  # as the message sets it
            for cb in gizmo._impl_aux.update_cb:  # what viser runs on a client's update
                cb(None)
            assert np.allclose(c._roi_centre, want), (crafted, c._roi_centre)
            lo, hi = c.roi()
            assert np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))
    finally:
        c.roi_edit.value = False
