"""Issue 26, item 4: outputs survive interruptions and concurrent runs, and only organlab's files are removed.

A kill between the two renames of the atomic replacement left no --out (the old result hidden in
.old-*), kill -9 while writing left .tmp-* folders for good, concurrent runs raced, a user's file
in --out/surface/ was deleted and calibrate --out overwrote a calibration.json without a word.
"""

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _hostile import copy_session, small_calibrated

from organlab.cli import main
from organlab.errors import OrganlabError
from organlab.preflight import atomic_output_dir, check_output_dir, lock_output_dir

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return small_calibrated(tmp_path_factory)


def _result(folder, text):
    folder.mkdir(parents=True)
    (folder / "report.json").write_text(text)
    (folder / "mesh.ply").write_text("ply")
    return folder


def test_interrupted_replacement_is_restored_and_leftovers_removed(tmp_path):
    out = tmp_path / "out"
    # what a kill between `rename(out, old)` and `rename(tmp, out)` leaves
    _result(tmp_path / ".out.old-k3j2", '{"run": 1}')
    _result(tmp_path / ".out.tmp-9x8y", '{"run": 2, "half": true}')
    with lock_output_dir(out) as notes:
        assert (out / "report.json").read_text() == '{"run": 1}'  # the previous result is back
    assert any("restored the previous result" in n and ".out.old-k3j2" in n for n in notes), notes
    assert any("removed .out.tmp-9x8y" in n for n in notes), notes
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no leftovers, no lock file


def test_old_result_beside_a_complete_one_is_removed(tmp_path):
    out = _result(tmp_path / "out", '{"run": 2}')
    _result(tmp_path / ".out.old-aaaa", '{"run": 1}')
    with atomic_output_dir(out) as tmp:
        (tmp / "report.json").write_text('{"run": 3}')
    assert (out / "report.json").read_text() == '{"run": 3}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_concurrent_run_into_the_same_out_refuses(tmp_path):
    out = tmp_path / "out"
    code = ("import sys, time\nfrom organlab.preflight import lock_output_dir\n"
            f"with lock_output_dir({str(out)!r}):\n    print('held', flush=True)\n    time.sleep(30)\n")
    holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                              env=dict(os.environ, PYTHONPATH=str(ROOT)))
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(OrganlabError, match=f"another organlab run \\(process {holder.pid}\\)"):
            with atomic_output_dir(out):
                pass
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()
    # the kernel released the killed holder's lock: the next run goes ahead and removes the stale file
    with atomic_output_dir(out) as tmp:
        (tmp / "report.json").write_text("{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_users_file_in_surface_is_never_removed(tmp_path):
    out = _result(tmp_path / "out", "{}")
    (out / "surface").mkdir()
    (out / "surface" / "mesh.ply").write_text("ply")  # organlab mesh's
    check_output_dir(out)
    (out / "surface" / "my notes.txt").write_text("keep me")
    with pytest.raises(OrganlabError, match="surface/my notes.txt"):
        with atomic_output_dir(out):
            pass
    assert (out / "surface" / "my notes.txt").read_text() == "keep me"


def test_calibrate_out_refuses_to_overwrite_without_force(small, tmp_path, capsys):
    dest = tmp_path / "cal"
    dest.mkdir()
    (dest / "calibration.json").write_text('{"mine": true}')
    assert main(["calibrate", str(small), "--out", str(dest), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "already exists" in err and "--force" in err and len(err.strip().splitlines()) == 1
    assert (dest / "calibration.json").read_text() == '{"mine": true}'
    assert main(["calibrate", str(small), "--out", str(dest), "--quiet", "--force"]) == 0
    assert "camera" in json.loads((dest / "calibration.json").read_text())


@pytest.mark.slow
def test_kill_9_at_random_points_then_the_same_command_leaves_a_complete_result(small, tmp_path):
    session = copy_session(small, tmp_path / "s")
    out = tmp_path / "runs" / "out"
    cmd = [sys.executable, "-m", "organlab", "reconstruct", str(session), "--out", str(out), "--voxel-size", "4",
           "--raw-surface", "--quiet"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, capture_output=True, timeout=300)
    full = time.perf_counter() - t0
    reference = json.loads((out / "report.json").read_text())
    rng = random.Random(26)
    killed_while = []
    for frac in sorted(rng.uniform(0.3, 1.0) for _ in range(3)):  # seeded: reproducible kill points
        p = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(frac * full)
        p.send_signal(signal.SIGKILL)
        p.wait()
        killed_while.append(sorted(x.name for x in out.parent.iterdir()))
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert sorted(x.name for x in out.parent.iterdir()) == ["out"], (killed_while, done.stderr)
    report = json.loads((out / "report.json").read_text())
    assert report["volume_mm3"] == reference["volume_mm3"] and report["grid"] == reference["grid"]
    assert {p.name for p in out.iterdir()} >= {"report.json", "voxels.npz", "mesh.ply", "mesh.stl", "calibration.json"}


def test_full_disk_while_writing_is_one_line_and_keeps_the_previous_result(tmp_path):
    import errno

    out = _result(tmp_path / "out", '{"run": 1}')
    with pytest.raises(OrganlabError) as e:
        with atomic_output_dir(out) as tmp:
            (tmp / "report.json").write_text("{}")
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp / "mesh.stl"))
    assert "No space left on device" in str(e.value) and "\n" not in str(e.value)
    assert (out / "report.json").read_text() == '{"run": 1}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_mesh_of_an_empty_model_is_one_line(tmp_path, capsys):
    import numpy as np

    np.savez_compressed(tmp_path / "voxels.npz", occupancy=np.zeros((4, 4, 4), bool), origin_mm=np.zeros(3),
                        voxel_size_mm=np.float64(2.0))
    assert main(["mesh", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "the model is empty" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "surface").exists()


def test_full_disk_during_capture_keeps_what_was_taken_and_a_rerun_completes(tmp_path, monkeypatch):
    import errno

    from organlab.capture import CaptureError, capture_session
    from organlab.synthetic import SimRig
    from organlab.capture import _session as cs

    real, calls = cs._write_png, []

    def full_after_5(root, rel, image):
        calls.append(rel)
        if len(calls) > 5:
            raise OSError(errno.ENOSPC, "No space left on device", str(root / rel))
        return real(root, rel, image)

    root = tmp_path / "s"
    monkeypatch.setattr(cs, "_write_png", full_after_5)
    with SimRig(time_scale=20.0, image_size=(320, 240)) as rig:
        with rig.turntable(timeout=0.2, poll_interval=0.005) as t, pytest.raises(CaptureError) as e:
            capture_session(root, t, rig.camera(), step_deg=90.0, n_background=1, intrinsics=rig.camera_model,
                            prompt=rig.prompt, say=lambda s: None)
    assert "No space left on device" in str(e.value) and "\n" not in str(e.value)
    doc = json.loads((root / "session.json").read_text())
    listed = doc["background_images"] + [x["image"] for x in doc["calibration"]["turntable_images"] + doc["views"]]
    assert len(listed) == 5 and all((root / p).is_file() for p in listed)  # nothing taken is lost
    monkeypatch.setattr(cs, "_write_png", real)
    with SimRig(time_scale=20.0, image_size=(320, 240)) as rig:
        with rig.turntable(timeout=0.2, poll_interval=0.005) as t:
            capture_session(root, t, rig.camera(), step_deg=90.0, n_background=1, intrinsics=rig.camera_model,
                            prompt=rig.prompt, say=lambda s: None)
    doc = json.loads((root / "session.json").read_text())
    assert doc["capture"]["complete"] and len(doc["views"]) == 4
