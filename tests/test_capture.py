"""Capture: the MCode driver over a real pty, the simulated rig, crash-safe sessions, the angle audit."""

import json
import os

import numpy as np
import pytest

from organlab.capture import (
    AngleAuditError,
    CameraError,
    DisconnectedError,
    FolderCamera,
    GarbledReplyError,
    MDriveTurntable,
    NoReplyError,
    OpenCVCamera,
    PositionError,
    StallError,
    capture_session,
)
from organlab.cli import main
from organlab.session import load_session
from organlab.synthetic import MDriveSimulator, SimCamera, SimRig

DRIVE = {"steps_per_rev": 200, "microsteps": 256, "gear_ratio": 90.0}
STEPS_PER_DEG = 200 * 256 * 90 / 360.0


@pytest.fixture
def sim():
    s = MDriveSimulator(steps_per_deg=STEPS_PER_DEG, start_steps=1234, time_scale=20.0)
    yield s
    s.close()


def _table(sim, **kw):
    opts = dict(DRIVE, home_switch=True, timeout=0.2, poll_interval=0.005)
    opts.update(kw)
    return MDriveTurntable(sim.port, **opts)


def test_setup_moves_and_homing_over_a_pty(sim):
    with _table(sim, speed_deg_s=45.0) as t:
        # the set-up reached the controller: echo mode, microsteps, currents, speed in microsteps/s
        assert sim.vars["EM"] == 1 and sim.vars["MS"] == 256 and sim.vars["RC"] == 75 and sim.vars["HC"] == 25
        assert sim.vars["VM"] == round(45.0 * STEPS_PER_DEG)
        assert t.home() == 0.0
        assert abs(sim.table_angle_deg()) < 1e-9  # homing found the switch (physical 0), not the power-up position
        assert t.move_to(30.0) == pytest.approx(30.0, abs=1e-4)
        assert sim.table_angle_deg() == pytest.approx(30.0, abs=1e-4)
        assert t.move_by(-12.5) == pytest.approx(17.5, abs=1e-4)
        assert sim.table_angle_deg() == pytest.approx(17.5, abs=1e-4)
    lines = t.log.lines
    assert any(line.endswith("> MA 384000") for line in lines)  # 30 deg * 12800 microsteps/deg
    assert any(line.endswith("> MR -160000") for line in lines)


def test_party_mode_addresses_the_device(tmp_path):
    s = MDriveSimulator(steps_per_deg=STEPS_PER_DEG, time_scale=20.0, party_name="A")
    try:
        with _table(s, device_name="A", log=tmp_path / "serial.log") as t:
            t.home()
            t.move_to(5.0)
        assert s.table_angle_deg() == pytest.approx(5.0, abs=1e-4)
        assert "> AMA 64000" in (tmp_path / "serial.log").read_text()
    finally:
        s.close()


def test_dropped_and_garbled_replies_are_retried(sim):
    with _table(sim) as t:
        t.home()
        sim.inject("drop", on="MA")
        sim.inject("garble", on="PR P")
        assert t.move_to(20.0) == pytest.approx(20.0, abs=1e-4)
        assert sim.table_angle_deg() == pytest.approx(20.0, abs=1e-4)
        kinds = [e["message"] for e in t.events if e["kind"] == "retry"]
        assert len(kinds) == 2 and "MA 256000" in kinds[0] and "PR P" in kinds[1]
        # a relative move whose answer is lost is not sent again blindly: the table turns once
        sim.inject("drop", on="MR")
        assert t.move_by(10.0) == pytest.approx(30.0, abs=1e-4)
        assert sum(c.startswith("MR") for c in sim.received) == 1
        sim.inject("drop", on="PR MV", count=10)
        with pytest.raises(NoReplyError, match=r"no reply to 'PR MV' after 3 tries") as e:
            t.move_to(40.0)
        assert "\n" not in str(e.value)
        sim.clear_faults()
        sim.inject("garble", on="PR P", count=10)
        with pytest.raises(GarbledReplyError, match="garbled reply to 'PR P'"):
            t.angle()


def test_lost_steps_are_detected_from_the_read_back(sim):
    with _table(sim) as t:
        t.home()
        sim.inject("lost_steps", steps=900)
        assert t.move_to(10.0) == pytest.approx(10.0, abs=1e-4)  # detected, moved again
        lost = [e for e in t.events if e["kind"] == "lost_steps"]
        assert len(lost) == 1 and lost[0]["steps"] == -900
        sim.inject("lost_steps", steps=900, count=5)
        with pytest.raises(PositionError, match="lost steps"):
            t.move_to(20.0)
        sim.clear_faults()
        sim.inject("stall", fraction=0.5)
        with pytest.raises(StallError, match=r"stalled during the move to 50 deg: at 34\.96\d deg, \d+ steps short"):
            t.move_to(50.0)  # from 19.93 deg (the uncorrected lost steps above), stopped half-way
        assert sim.table_angle_deg() == pytest.approx(t.angle(), abs=1e-4)


def test_unplugged_port_and_missing_port_are_clear_errors(sim):
    with _table(sim) as t:
        t.home()
        sim.inject("unplug", on="MA")
        with pytest.raises(DisconnectedError, match="still plugged in"):
            t.move_to(10.0)
    with pytest.raises(DisconnectedError, match=r"/dev/organlab-no-such-port: cannot open the serial port"):
        MDriveTurntable("/dev/organlab-no-such-port")


def test_cameras_folder_replay_averaging_and_unplugged(tmp_path):
    rig = SimRig(image_size=(160, 120), noise_sigma=4.0, time_scale=20.0)
    try:
        one = rig.camera(average=1).grab()
        avg = rig.camera(average=16).grab()
        clean = rig.camera()._clean()
        # noise 4 grey levels, averaged over 16 frames: about 1 (quantization adds 0.29)
        assert np.std(one - clean) == pytest.approx(4.0, rel=0.15)
        assert np.std(avg - clean) < 1.3
    finally:
        rig.close()
    import cv2

    for i in range(2):
        cv2.imwrite(str(tmp_path / f"{i}.png"), np.full((12, 16, 3), 40 * (i + 1), np.uint8))
    cam = FolderCamera(tmp_path)
    assert cam.grab()[0, 0, 0] == 40 and cam.grab()[0, 0, 0] == 80
    with pytest.raises(CameraError, match="all 2 images replayed"):
        cam.grab()
    with pytest.raises(CameraError, match="cannot be opened; is it plugged in"):
        OpenCVCamera(str(tmp_path / "no-such-stream.mjpg"))


# ---------------------------------------------------------------- sessions
def _listed(doc):
    cal = doc["calibration"]
    names = list(doc["background_images"]) + list(cal["intrinsic_images"])
    names += [e["image"] for e in cal["turntable_images"]] + [e["image"] for e in doc["views"]]
    return names + [e["image"] for e in doc["capture"]["flagged"]]


def _on_disk(root):
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*.png"))


def _capture(root, rig, **kw):
    opts = dict(step_deg=60.0, n_background=2, intrinsics=rig.camera_model, reference={"volume_mm3": rig.volume_mm3}, prompt=rig.prompt, say=lambda s: None)
    opts.update(kw)
    with rig.turntable(timeout=0.2, poll_interval=0.005) as t:
        return capture_session(root, t, rig.camera(), **opts)


@pytest.mark.slow
def test_simulated_capture_calibrates_and_reconstructs_to_the_true_volume(tmp_path):
    from organlab.pipeline import reconstruct

    root = tmp_path / "sim"
    seen = []
    with SimRig(image_size=(640, 480), supersample=2, board_supersample=1, time_scale=20.0) as rig:
        with rig.turntable(timeout=0.3, poll_interval=0.005) as t:
            capture_session(root, t, rig.camera(), step_deg=20.0, n_background=5, n_intrinsic=12,
                            reference={"volume_mm3": rig.volume_mm3}, prompt=rig.prompt,
                            on_view=lambda i, a, img: seen.append((i, a, img.shape)), say=lambda s: None)
        volume = rig.volume_mm3
    doc = json.loads((root / "session.json").read_text())
    assert doc["capture"]["complete"] and "camera" not in doc  # intrinsics to be calibrated from the hand-held images
    assert [a for _, a, _ in seen] == [20.0 * i for i in range(18)] and seen[0][2] == (480, 640, 3)
    assert [e["angle_deg"] for e in doc["calibration"]["turntable_images"]] == [e["angle_deg"] for e in doc["views"]]
    # the audit measured every stop from its board image: within 0.05 deg here (measured max 0.01 deg at 640x480
    # earlier; 0.048 deg on 2026-12-03, twice, by a script with this test's settings: near the bound, to look into)
    errors = [abs(a["error_deg"]) for a in doc["capture"]["audit"]]
    assert len(errors) == 18 and max(errors) < 0.05 and not doc["capture"]["flagged"]
    log = (root / "capture" / "serial.log").read_text()
    assert log.count("> MA ") == 36 and "> PR MV" in log and "> HM 1" in log
    assert sorted(_listed(doc)) == _on_disk(root)
    rec = reconstruct(load_session(root), voxel_size=2.0)
    err = rec.report["mesh_volume_error_pct"]
    assert rec.report["watertight"]
    # sample-session tolerance at 2 mm: 1 %; measured -0.13 % (18 views; 36 views at step 10 give -0.75 %)
    assert abs(err) < 1.0, err
    assert rec.session.reference["volume_mm3"] == pytest.approx(volume)


@pytest.mark.parametrize("fault", ["stall", "unplug"])
def test_a_capture_that_dies_keeps_its_images_and_a_second_run_completes_it(tmp_path, fault):
    root = tmp_path / "s"
    with SimRig(time_scale=20.0) as rig:
        # the 3rd move of the views pass (6 stops: 1 homing + 6 board moves + 2 view moves before it)
        rig.controller.inject(fault, on="MA", after=8)
        rig.controller.inject("drop", on="PR P", after=3)  # retried; recorded in session.json
        with pytest.raises(StallError if fault == "stall" else DisconnectedError) as e:
            _capture(root, rig)
    assert "\n" not in str(e.value)
    doc = json.loads((root / "session.json").read_text())
    assert doc["capture"]["last_error"] == str(e.value) and not doc["capture"]["complete"]
    assert [ev["kind"] for ev in doc["capture"]["events"]] == ["retry"] and "'PR P'" in doc["capture"]["events"][0]["message"]
    assert len(doc["views"]) == 2 and len(doc["calibration"]["turntable_images"]) == 6
    assert sorted(_listed(doc)) == _on_disk(root)  # every image taken is on disk and listed
    before = {p: os.stat(root / p).st_mtime_ns for p in _on_disk(root)}
    (root / "views" / "120.png").write_bytes(b"half-written")  # a crash between the image and session.json
    with SimRig(time_scale=20.0, start_deg=-40.0) as rig:  # powered again elsewhere: homing finds 0
        _capture(root, rig)
    doc = json.loads((root / "session.json").read_text())
    assert doc["capture"]["complete"] and "last_error" not in doc["capture"]
    assert [v["angle_deg"] for v in doc["views"]] == [0.0, 60.0, 120.0, 180.0, 240.0, 300.0]
    assert doc["views"][2]["image"] == "views/120_1.png"  # never overwritten
    assert all(os.stat(root / p).st_mtime_ns == t for p, t in before.items())
    assert load_session(root).reference["volume_mm3"] > 0


class _SlippingCamera(SimCamera):
    """The plate slips by 2 degrees on the shaft after the 2nd board image (the controller cannot know)."""

    def grab(self, **kw):
        if self.rig.scene == "board":
            self.boards = getattr(self, "boards", 0) + 1
            if self.boards == 3:
                self.rig.slip_deg = 2.0
        return super().grab(**kw)


def test_angle_audit_flags_a_slipping_plate_before_any_view(tmp_path):
    root = tmp_path / "s"
    with SimRig(time_scale=20.0) as rig:
        with rig.turntable(timeout=0.2, poll_interval=0.005) as t, pytest.raises(AngleAuditError, match=r"120 deg \(\+2\.0\d deg, limit 0\.5\)"):
            capture_session(root, t, _SlippingCamera(rig), step_deg=60.0, n_background=2, intrinsics=rig.camera_model,
                            prompt=rig.prompt, say=lambda s: None)
        doc = json.loads((root / "session.json").read_text())
        assert doc["views"] == [] and len(doc["calibration"]["turntable_images"]) == 2
        flag = doc["capture"]["flagged"][0]
        assert flag["commanded_deg"] == 120.0 and flag["error_deg"] == pytest.approx(2.0, abs=0.1)
        rig.slip_deg = 0.0  # plate fixed; run again: the flagged stop is retaken, then the views
        _capture(root, rig)
    doc = json.loads((root / "session.json").read_text())
    assert doc["capture"]["complete"] and len(doc["views"]) == 6
    assert sorted(e["angle_deg"] for e in doc["calibration"]["turntable_images"]) == [0, 60, 120, 180, 240, 300]
    assert max(abs(a["error_deg"]) for a in doc["capture"]["audit"]) < 0.1  # 320x240: measured < 0.05 deg


def test_angle_audit_catches_a_wrong_gear_ratio(tmp_path):
    # the driver believes 72:1, the table is 90:1: 60 deg commanded turns the table 48 deg
    with SimRig(time_scale=20.0) as rig:
        with rig.turntable(gear_ratio=72.0, timeout=0.2, poll_interval=0.005) as t, pytest.raises(AngleAuditError) as e:
            capture_session(tmp_path / "s", t, rig.camera(), step_deg=60.0, n_background=1, intrinsics=rig.camera_model,
                            prompt=rig.prompt, say=lambda s: None)
    assert "for commanded 60 deg" in str(e.value) and "\n" not in str(e.value)
    flag = json.loads((tmp_path / "s" / "session.json").read_text())["capture"]["flagged"][0]
    assert flag["measured_deg"] == pytest.approx(48.0, abs=0.1)  # 320x240: measured 48.04


def test_capture_command_line(tmp_path, capsys):
    out = tmp_path / "cli"
    args = ["capture", "--turntable", "sim", "--step", "90", "--out", str(out), "--background", "2", "--sim-size", "320x240", "--quiet"]
    assert main(args) == 0
    doc = json.loads((out / "session.json").read_text())
    assert doc["capture"]["complete"] and len(doc["views"]) == 4 and doc["reference"]["volume_mm3"] > 1e5
    assert main(args) == 0  # nothing left to do: the complete session is left as it is
    assert len(json.loads((out / "session.json").read_text())["views"]) == 4
    capsys.readouterr()
    assert main(["capture", "--turntable", "sim", "--step", "30", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("organlab: error: ") and "capture.step_deg is 90.0 but this run asks 30.0" in err and "\n" not in err
    assert main(["capture", "--turntable", "/dev/organlab-no-such-port", "--camera", "0", "--out", str(tmp_path / "x"), "--quiet"]) == 2
    assert "cannot open the serial port" in capsys.readouterr().err


def test_camera_lost_mid_capture_keeps_the_session(tmp_path, sim):
    import cv2

    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(8):
        cv2.imwrite(str(frames / f"{i:02d}.png"), np.full((24, 32, 3), 10 * i, np.uint8))
    root = tmp_path / "s"
    opts = dict(step_deg=90.0, n_background=2, board=False, prompt=lambda *a: None, say=lambda s: None)
    with _table(sim) as t:
        cam = FolderCamera(frames)
        cam.files = cam.files[:4]  # the camera dies after 4 frames: 2 backgrounds, 2 views
        with pytest.raises(CameraError, match="all 4 images replayed"):
            capture_session(root, t, cam, **opts)
        doc = json.loads((root / "session.json").read_text())
        assert len(doc["background_images"]) == 2 and [v["angle_deg"] for v in doc["views"]] == [0.0, 90.0]
        assert sorted(_listed(doc)) == _on_disk(root) and doc["image_size"] == [32, 24]
        cam = FolderCamera(frames)
        cam.files = cam.files[4:]
        capture_session(root, t, cam, **opts)
    doc = json.loads((root / "session.json").read_text())
    assert doc["capture"]["complete"] and [v["angle_deg"] for v in doc["views"]] == [0.0, 90.0, 180.0, 270.0]
    # the 3rd view is the 5th frame (value 40): the second run took up exactly where the first stopped
    assert cv2.imread(str(root / doc["views"][2]["image"]))[0, 0, 0] == 40
    assert sim.table_angle_deg() == pytest.approx(270.0, abs=1e-4)
