"""organlab capture --view: the live viewer follows a simulated capture (server side, no browser)."""

import numpy as np
import pytest

pytest.importorskip("viser")


def _frustums(live):
    return sorted(n for n in live.server.scene._handle_from_node_name if n.startswith("/views/"))


def _check_scene(viewer, root):
    """One frustum per view at its calibrated camera, and the progressive hull of the views' silhouettes."""
    from organlab.carving import carve
    from organlab.pipeline import session_cameras
    from organlab.session import load_session
    from organlab.silhouette import silhouettes
    from organlab.viewer._scene import surface_voxels

    live = viewer.live
    s = load_session(root)
    cams = session_cameras(s)
    assert viewer.error is None and len(s.views) == 6
    assert _frustums(live) == [f"/views/{i:03d}" for i in range(6)]
    for cam, shown in zip(cams, live.cameras):  # each frustum stands at its view's calibrated camera
        np.testing.assert_allclose(shown.center, cam.center, atol=1e-6)
    occ = viewer.hull.occupancy
    grid = viewer.hull.grid
    assert grid.voxel_size == 2.0 and occ.any()
    # the hull shown is the one of the session's silhouettes (same automatic thresholds)
    np.testing.assert_array_equal(occ, carve(silhouettes(s), cams, grid))
    assert len(live._handles["voxels"].points) == surface_voxels(occ).sum()
    # a hull holds the specimen and, from 6 views, exceeds it: measured 1.31 x the exact
    # volume (320x240 images, 2 mm voxels); a lost view or a wrong pose gives > 2 x or < 1 x
    ratio = grid.volume_of(occ) / s.reference["volume_mm3"]
    assert 1.0 < ratio < 2.0, ratio


def test_capture_command_line_view(tmp_path, capsys, monkeypatch):
    import organlab.cli as cli

    seen = {}

    def serve(viewer):  # instead of waiting for Ctrl-C: look at the scene the capture left
        seen["port"] = viewer.live.port
        _check_scene(viewer, tmp_path / "s")
        seen["checked"] = True

    monkeypatch.setattr(cli, "_serve_until_interrupted", serve)
    args = ["capture", "--turntable", "sim", "--step", "60", "--out", str(tmp_path / "s"), "--background", "2",
            "--sim-size", "320x240", "--quiet", "--view", "--port", "0"]
    assert cli.main(args) == 0
    out = capsys.readouterr().out
    assert seen.get("checked") and f"live view at http://127.0.0.1:{seen['port']}" in out
    assert cli.main(["capture", "--turntable", "sim", "--out", str(tmp_path / "x"), "--no-board", "--view", "--quiet"]) == 2
    assert "--view needs the board images" in capsys.readouterr().err


def test_continued_capture_shows_the_earlier_views(tmp_path):
    """A capture that died after 2 views, continued with the viewer: all 6 views and their hull."""
    from organlab.capture import StallError, run_capture
    from organlab.viewer import CaptureViewer

    root = tmp_path / "s"
    opts = dict(step_deg=60.0, n_background=2, sim_options={"image_size": (320, 240), "time_scale": 20.0},
                say=lambda s: None)
    # the 3rd move of the views pass (1 homing + 6 board moves + 2 view moves before it)
    with pytest.raises(StallError):
        run_capture(root, sim_faults=[{"kind": "stall", "on": "MA", "after": 8}], **opts)
    notes = []
    with CaptureViewer(root, port=0, say=notes.append) as viewer:
        run_capture(root, on_view=viewer.on_view, **opts)
        assert not notes
        _check_scene(viewer, root)


def test_viewer_without_poses_says_so_once_and_the_capture_completes(tmp_path):
    import json

    from organlab.capture import run_capture
    from organlab.viewer import CaptureViewer

    notes = []
    with CaptureViewer(tmp_path / "s", port=0, say=notes.append) as viewer:
        run_capture(tmp_path / "s", step_deg=90.0, n_background=2, board=False, on_view=viewer.on_view,
                    sim_options={"image_size": (320, 240), "time_scale": 20.0}, say=lambda s: None)
        assert len(notes) == 1 and "live view off" in notes[0] and "no turntable calibration" in notes[0]
        assert viewer.live.cameras == []
    assert json.loads((tmp_path / "s" / "session.json").read_text())["capture"]["complete"]
