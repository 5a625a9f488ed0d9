"""Sweeps and batches on Dask (issue 23): a real LocalCluster of 2 worker processes against the serial fallback.

One cluster and one serial reference sweep serve the whole module (2 mm voxels, raw surfaces, no AAA
measures: the distributed machinery is under test, not the surface stage).
"""

from __future__ import annotations

import json
import os
import pickle
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import organlab as ol
import organlab.batch as ob
from organlab.calibration import Calibration
from organlab.session import load_session
from tests._shared_data import sample_calibrated

pytest.importorskip("distributed")
pd = pytest.importorskip("pandas")

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_sessions" / "aaa_phantom"
# 6 thresholds x 2 tolerances = 12 settings in 6 tasks (each task: one threshold's silhouettes, both tolerances)
GRID = {"threshold": [10.0, 15.0, 20.0, 25.0, 30.0, 35.0], "tolerance": [0, 1]}
BASE = {"voxel_size": 2.0, "finish": False, "measure": False}
TIME_COLUMNS = ("seconds", "cpu_seconds", "status", "stages_run")


@pytest.fixture(scope="module")
def session():
    return load_session(SAMPLE)


@pytest.fixture(scope="module")
def calibration(session, tmp_path_factory):
    # one calibration for every run of the module: OpenCV's fit differs in the last digits from one call to the
    # next (measured: two calibrate() calls in one process give different K), and these runs compare bit for bit.
    # Set-up only: the sample's calibration computed once per run, shared with test_trust.py (each sweep task
    # checks it against the session, as calibration_for does any calibration it is given)
    return Calibration.load(sample_calibrated(tmp_path_factory) / "calibration.json", image_size=session.image_size)


@pytest.fixture(scope="module")
def client():
    with ob.dask_client(workers=2) as c:
        yield c


@pytest.fixture(scope="module")
def serial(tmp_path_factory, session, calibration):
    out = tmp_path_factory.mktemp("serial")
    df = ob.sweep(session, GRID, settings=BASE, out=out, calibration=calibration, workers=0)
    return out, df


def _npz(path):
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _assert_same_result(a, b):
    """Two result folders hold the same reconstruction (every file bit for bit; report.json but its timings)."""
    ra, rb = (json.loads((d / "report.json").read_text()) for d in (a, b))
    ra.pop("timings_s"), rb.pop("timings_s")
    # the pose stage's diagnostics (tangent residuals, the gate's medians) differ in their last digits between a
    # worker process and this one; its decision and the cameras it leaves (in views[i].R, t) must be the same
    pa, pb = ra.pop("poses", {}), rb.pop("poses", {})
    assert {k: pa.get(k) for k in ("mode", "accepted", "model")} == {k: pb.get(k) for k in ("mode", "accepted", "model")}
    assert ra == rb, a.name
    for name in ("mesh.ply", "mesh.stl", "calibration.json"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), f"{a.name}/{name}"
    za, zb = _npz(a / "voxels.npz"), _npz(b / "voxels.npz")
    assert za.keys() == zb.keys()
    for k in za:
        assert np.array_equal(za[k], zb[k]), f"{a.name}/voxels.npz:{k}"


def _assert_same_table(a, b):
    cols = [c for c in a.columns if c not in TIME_COLUMNS and not c.startswith("time_")]
    pd.testing.assert_frame_equal(a[cols].reset_index(drop=True), b[cols].reset_index(drop=True))


def _worker_setup():
    import dask

    return (os.environ.get("MALLOC_TRIM_THRESHOLD_"), dask.config.get("distributed.worker.profile.enabled"),
            dask.config.get("distributed.admin.tick.interval"))


def _listening(pids):
    import psutil

    out = []
    for pid in pids:
        try:
            conns = psutil.Process(pid).net_connections(kind="inet")
        except psutil.Error:
            continue
        out += [(pid, c.laddr) for c in conns if c.status == psutil.CONN_LISTEN]
    return out


def test_the_local_cluster_is_two_single_threaded_processes_on_loopback_only(client):
    import psutil

    info = client.scheduler_info(n_workers=-1)
    assert info["address"].startswith("tcp://127.0.0.1:")
    workers = info["workers"]
    assert len(workers) == 2 and all(w["nthreads"] == 1 for w in workers.values())
    assert all(a.startswith("tcp://127.0.0.1:") for a in workers)
    pids = client.run(os.getpid)
    assert len(set(pids.values()) | {os.getpid()}) == 3  # worker processes, not threads of this one

    def numba_threads():
        import numba

        return numba.get_num_threads()

    assert set(client.run(numba_threads).values()) == {1}
    # glibc's malloc as in any process: Dask's default MALLOC_TRIM_THRESHOLD_=65536 made every array of more than
    # 128 kB a fresh mapping (the colouring stage took 4.7 s CPU in a worker against 3.0 s without it, measured)
    # and no statistical profiler, calmer periodic checks (organlab.batch._run.WORKER_CONFIG)
    assert set(client.run(_worker_setup).values()) == {(None, False, "1s")}
    # nothing of the cluster (scheduler and nannies in this process, the workers in theirs) listens beyond loopback
    ours = [os.getpid(), *pids.values(), *(p.pid for p in psutil.Process().children(recursive=True))]
    socks = _listening(ours)
    assert socks, "the scheduler listens somewhere"
    assert all(addr.ip in ("127.0.0.1", "::1") for _, addr in socks), socks


def test_twelve_settings_on_a_local_cluster_are_identical_to_the_serial_fallback(client, serial, session, calibration,
                                                                                  tmp_path):
    ref_out, ref = serial
    t0 = time.time()
    df = ob.sweep(session, GRID, settings=BASE, out=tmp_path, calibration=calibration, client=client)
    assert len(df) == 12 and (df["status"] == "done").all() and (ref["status"] == "done").all()
    # the client hands out the work: every threshold's shared first stages (6 prefixes, of unknown cost: the pose
    # fit runs at 35 only) start before any task that goes on from them, and one task per worker runs at a time
    # (Dask's own queue had started the prefix of threshold 35 last, behind the tasks already placed); read in the
    # scheduler's own log of its tasks' transitions (the workers' clocks differ from its by a varying offset)
    log = [t for t in client.cluster.scheduler.transition_log if t.timestamp >= t0 and str(t.key).startswith("organlab-")]
    started, running, most = [], 0, 0
    for t in log:
        if t.finish == "processing":
            started.append(str(t.key))
            running += 1
            most = max(most, running)
        elif t.start == "processing":
            running -= 1
    kinds = ["prefix" if k.startswith("organlab-prefix-") else "task" for k in started]
    assert kinds == ["prefix"] * 6 + ["task"] * 12, started
    assert most == 2
    _assert_same_table(df, ref)
    # work shared: each task computed one threshold's silhouettes once, for both tolerances
    for stages in (df, ref):
        runs = stages.set_index(["threshold", "tolerance"])["stages_run"]
        for t in GRID["threshold"]:
            assert runs[(t, 0)].split(",")[:2] == ["calibration", "silhouettes"], runs[(t, 0)]
            assert runs[(t, 1)].split(",")[0] == "carving", runs[(t, 1)]
    for name in df["name"]:
        _assert_same_result(tmp_path / "results" / name, ref_out / "results" / name)
    # the results are reconstructions, not placeholders: at threshold 10 and tolerance 0 the carved volume is
    # within 0.5 % of the phantom's (measured -0.02 %), and every threshold step carves less
    hull = df[df["tolerance"] == 0].sort_values("threshold")
    assert abs(hull["volume_error_pct"].iloc[0]) < 0.5
    assert (np.diff(hull["volume_mm3"].to_numpy()) < 0).all()
    # a tolerance of one view keeps more voxels at every threshold
    tol = df[df["tolerance"] == 1].sort_values("threshold")
    assert (tol["volume_mm3"].to_numpy() > hull["volume_mm3"].to_numpy()).all()


def test_the_summary_plots_and_recommended_setting_are_written(serial):
    out, df = serial
    back = pd.read_csv(out / "summary.csv")
    assert list(back["name"]) == list(df["name"])
    assert np.allclose(back["volume_mm3"], df["volume_mm3"]) and np.allclose(back["agreement_mean_iou"], df["agreement_mean_iou"])
    for col in ("agreement_worst_iou", "worst_view", "n_warnings", "watertight", "seconds", "time_carving_s"):
        assert col in back
    assert (back["agreement_worst_iou"] <= back["agreement_mean_iou"]).all()
    rec = json.loads((out / "recommended.json").read_text())
    assert rec == json.loads(json.dumps(df.attrs["recommended"], default=str))
    for x in ("threshold", "tolerance"):
        png = out / "plots" / f"volume_agreement_vs_{x}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not [p for p in (out / "results").iterdir() if p.name.startswith(".")]


def test_the_recommended_threshold_lies_on_the_plateau(serial):
    _, df = serial
    hull = df[df["tolerance"] == 0]
    rec = ob.recommend(hull)
    row = hull[hull["name"] == rec["name"]].iloc[0]
    # the sample's volume against the threshold: -0.02 % at 10, -0.22 % at 15, -0.46 % at 20, -0.84 % at 25,
    # -1.6 % at 30, then -13.6 % at 35 (the silhouettes lose the thin parts); the plateau is 10-30
    assert rec["plateau"] == [10.0, 15.0, 20.0, 25.0, 30.0], rec
    assert 10.0 < row["threshold"] < 30.0  # inside, not at the plateau's edges (measured: 15, the best agreement)
    assert abs(row["volume_error_pct"]) < 0.5, rec
    assert f"threshold {row['threshold']:g}" in rec["reason"] and "plateau 10-30" in rec["reason"]
    # over both tolerances the best agreement is tolerance 1's (IoU 0.9896 against 0.9882 at threshold 15: a model
    # allowed to leave one view's silhouette covers them all better) although it inflates the volume by 0.9 %:
    # agreement measures consistency with the silhouettes, not accuracy (docs/scale.md says so)
    both = df.attrs["recommended"]
    assert both["settings"]["threshold"] in both["plateau"]


def test_a_worker_killed_mid_sweep(client, serial, session, calibration, tmp_path):
    ref_out, _ = serial
    grid = {"threshold": [10.0, 15.0, 20.0], "tolerance": [0]}
    killed = {}

    def kill_one_busy_worker():
        t0 = time.monotonic()
        while time.monotonic() - t0 < 120 and not killed:
            busy = {w: keys for w, keys in client.processing().items() if keys}
            if busy:
                time.sleep(1.0)  # well into the task (each takes a few seconds at 2 mm)
                w = next(iter(busy))
                pid = client.run(os.getpid, workers=[w])[w]
                os.kill(pid, signal.SIGKILL)
                killed.update(worker=w, pid=pid)
                return
            time.sleep(0.05)

    killer = threading.Thread(target=kill_one_busy_worker)
    killer.start()
    df = ob.sweep(session, grid, settings=BASE, out=tmp_path, calibration=calibration, client=client)
    killer.join()
    assert killed, "no worker was busy"
    assert (df["status"] == "done").all(), df[["name", "status", "error"]]
    results = tmp_path / "results"
    assert sorted(p.name for p in results.iterdir()) == sorted(df["name"])  # no temporary or half-written folder
    for name in df["name"]:
        _assert_same_result(results / name, ref_out / "results" / name)
    client.wait_for_workers(2, timeout=60)  # the nanny restarted the killed one
    assert killed["pid"] not in client.run(os.getpid).values()
    assert set(client.run(_worker_setup).values()) == {(None, False, "1s")}  # the restarted worker's too

    # re-running finishes nothing twice: every result is taken as it is
    stamps = {p.name: p.stat().st_mtime_ns for p in results.iterdir()}
    again = ob.sweep(session, grid, settings=BASE, out=tmp_path, calibration=calibration, client=client)
    assert (again["status"] == "finished before").all()
    assert {p.name: p.stat().st_mtime_ns for p in results.iterdir()} == stamps
    _assert_same_table(again, df)


def _small_session(root, specimen, seed):
    """A scene the defaults were never tuned on: 320 x 240, 12 views, the true cameras given."""
    from organlab.synthetic import make_session

    truth = make_session(root, specimen=specimen, image_size=(320, 240), n_views=12, n_background=5, views_only=True,
                         seed=seed, supersample=1)
    return root, truth["volume_mm3"]


@pytest.fixture(scope="module")
def grooved(tmp_path_factory):
    return _small_session(tmp_path_factory.mktemp("grooved") / "grooved", "grooved", 5)


def test_a_batch_of_three_sessions_one_broken(client, grooved, tmp_path):
    dented = _small_session(tmp_path / "dented", "dented", 6)
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "session.json").write_text(json.dumps({"format": "organlab.session/1", "name": "broken",
                                                     "views": [{"image": "views/000.png", "angle_deg": 0}]}))
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "organlab", "batch", str(grooved[0]), str(broken), str(dented[0]), "--out", str(out),
           "--voxel-size", "2", "--raw-surface", "--quiet", "--scheduler", client.scheduler.address]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=ROOT, env=env)
    assert r.returncode == 2, r.stderr[-3000:]
    errors = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(errors) == 1 and errors[0].startswith("organlab: error: broken: ") and "session.json" in errors[0], r.stderr
    assert "Traceback" not in r.stderr
    assert "3 sessions (2 computed, 0 finished before, 1 failed)" in r.stdout
    df = pd.read_csv(out / "summary.csv")
    assert list(df["name"]) == ["grooved", "broken", "dented"]
    assert list(df["status"]) == ["done", "error", "done"]
    assert sorted(p.name for p in (out / "results").iterdir()) == ["dented", "grooved"]
    # both are real reconstructions: a visual hull holds its specimen and, from 12 views, the air of its grooves
    # or dent too: the grooved one +4.3 %, the dented one +8.1 % (measured)
    for name, volume, bound in (("grooved", grooved[1], 0.08), ("dented", dented[1], 0.12)):
        got = json.loads((out / "results" / name / "report.json").read_text())["volume_mm3"]
        assert 0 < got / volume - 1 < bound, (name, got / volume - 1)


def test_a_sweep_on_a_scene_the_defaults_never_saw(grooved):
    root, volume = grooved
    df = ol.sweep(root, {"threshold": [None, 5.0, 10.0, 15.0, 20.0, 30.0, 45.0]}, settings={"voxel_size": 2.0, "finish": False})
    assert (df["status"] == "done").all()
    rec = df.attrs["recommended"]
    row = df[df["name"] == rec["name"]].iloc[0]
    # measured: the same volume at 5-20 (sharp-edged renders), -0.4 % to 30, -59 % to 45 (the silhouettes break up)
    assert rec["plateau"][0] == 5.0 and 20.0 <= rec["plateau"][-1] <= 30.0, rec
    assert 5.0 < row["threshold"] < rec["plateau"][-1]
    # its hull holds the specimen, plus the grooves' air 12 views cannot carve (+4.3 % measured)
    assert 0 < row["volume_mm3"] / volume - 1 < 0.08
    # and it agrees with Li's automatic threshold within 1 % (the same volume, measured)
    auto = df[df["threshold"].isna()].iloc[0]
    assert abs(row["volume_mm3"] / auto["volume_mm3"] - 1) < 0.01
    # the cliff is not on the plateau
    assert df[df["threshold"] == 45.0]["volume_mm3"].iloc[0] < 0.5 * row["volume_mm3"]


def test_workers_load_pymeshlab_in_their_main_thread_and_close_without_a_heap_error(grooved, tmp_path):
    """`organlab sweep --workers 2` with finished surfaces (pymeshlab in the workers): no glibc heap message.

    glibc printed ``malloc_consolidate(): unaligned fastbin chunk detected`` as the LocalCluster's workers
    closed, after every result was back (measured on the 12-setting benchmark at 2 mm, once per worker):
    pymeshlab was first loaded in the worker's task thread.  Each worker now loads numba's threads and then
    pymeshlab in its main thread as it starts (organlab.batch._run.start_libraries, a worker plugin).
    """
    root, _ = grooved
    # two finished hulls, a task for each worker (the colouring, also run here until 2026-12-03, loads nothing more
    # into a worker: the start-up plugin has loaded pymeshlab in both before their first task)
    cmd = [sys.executable, "-m", "organlab", "sweep", str(root), "--out", str(tmp_path / "out"), "--threshold", "10,20",
           "--method", "hull", "--voxel-size", "4", "--workers", "2", "--quiet"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert r.returncode == 0, r.stderr[-3000:]
    assert "malloc" not in r.stderr and "free()" not in r.stderr and "Aborted" not in r.stderr, r.stderr[-3000:]
    df = pd.read_csv(tmp_path / "out" / "summary.csv")
    assert len(df) == 2 and (df["status"] == "done").all()
    assert all(json.loads((tmp_path / "out" / "results" / n / "report.json").read_text())["surface"] for n in df["name"])


def test_the_worker_plugin_loads_pymeshlab_in_the_main_thread(client):
    def where():
        import threading

        return "pymeshlab" in sys.modules, threading.current_thread() is threading.main_thread()

    client.register_plugin(ob._run.worker_plugin(), name="organlab-start-libraries")
    # client.run runs in the worker's event loop, where the plugin's setup ran: the main thread
    assert set(client.run(where).values()) == {(True, True)}


# ---------------------------------------------------------------------------------------------- the parts, fast
def test_parse_values():
    assert ob.parse_values("10:40:5", name="threshold") == [10, 15, 20, 25, 30, 35, 40]
    assert ob.parse_values("0.1:0.3:0.1", name="voxel_size") == [0.1, 0.2, 0.3]  # no accumulated rounding
    assert ob.parse_values("2,1,2", name="voxel_size") == [2.0, 1.0]
    assert ob.parse_values("auto,12", name="threshold") == [None, 12.0]
    assert ob.parse_values("0:2:1", name="tolerance") == [0, 1, 2]
    for bad in ("10:5:1", "1:2", "a,b", "1:2:0"):
        with pytest.raises(ValueError, match="threshold"):
            ob.parse_values(bad, name="threshold")


def test_settings_sharing_their_silhouettes_share_a_task():
    settings = ob.expand({"threshold": [10.0, 20.0], "voxel_size": [2.0, 1.0], "method": ["hull", "coloring"]})
    assert len(settings) == 8
    tasks = ob.plan_tasks(settings, n_workers=2)
    assert len(tasks) == 2 and sorted(len(t) for t in tasks) == [4, 4]
    for t in tasks:
        assert len({s.threshold for s in t}) == 1
        # a carving's settings run one after another (the engine keeps the carving for the next method)
        sizes = [s.voxel_size for s in t]
        assert sizes[0] == sizes[1] != sizes[2] == sizes[3]
    # fewer groups than workers: the largest is split (along voxel sizes), so no worker idles
    one = ob.plan_tasks(ob.expand({"voxel_size": [2.0, 1.0], "method": ["hull", "coloring"]}), n_workers=2)
    assert len(one) == 2 and all(len({s.voxel_size for s in t}) == 1 for t in one)
    assert ob.plan_tasks(settings[:1], n_workers=4) == [[settings[0]]]


def test_result_names_depend_on_the_settings_alone():
    a = ob.expand({"threshold": [10.0]}, ob.Settings(voxel_size=2.0))[0]
    b = ob.expand({"voxel_size": [2.0], "threshold": [10.0, 20.0]})[0]
    assert ob.result_name(a) == ob.result_name(b) == "voxel-2_threshold-10_hull"
    names = {ob.result_name(s) for s in ob.expand({"threshold": [None, 10.0, 10.5], "tolerance": [0, 1]})}
    assert len(names) == 6
    with pytest.raises(ValueError, match="grid: unknown setting 'thresh'"):
        ob.expand({"thresh": [1]})
    with pytest.raises(ValueError, match="voxel_size"):
        ob.expand({"voxel_size": [-1.0]})


def _table(volumes, ious, thresholds):
    return pd.DataFrame({"name": [f"t{t}" for t in thresholds], "status": "done", "threshold": thresholds,
                         "method": "hull", "volume_mm3": volumes, "agreement_mean_iou": ious,
                         "agreement_worst_iou": np.asarray(ious) - 0.01})


def test_recommend_picks_the_plateau_not_the_best_agreement_off_it():
    # a curve with a noisy start (volume falls fast), a plateau at 20-40, a cliff after 40; the best agreement
    # of all is at 10, off the plateau
    t = [5.0, 10.0, 20.0, 30.0, 40.0, 50.0]
    rec = ob.recommend(_table([130.0, 115.0, 101.0, 100.5, 100.0, 80.0], [0.90, 0.99, 0.95, 0.97, 0.96, 0.90], t))
    assert rec["plateau"] == [20.0, 30.0, 40.0] and rec["name"] == "t30.0"
    # no two neighbouring thresholds within 1 %: no plateau, said so
    rec = ob.recommend(_table([130.0, 115.0, 101.0], [0.90, 0.99, 0.95], t[:3]))
    assert rec["plateau"] == [] and rec["reason"].startswith("no plateau")


def test_cli_errors_are_one_line(tmp_path):
    from organlab.cli import main

    for argv, what in ((["--threshold", "10:5:1"], "--threshold"), (["--workers", "2", "--scheduler", "tcp://127.0.0.1:1"], "exclude")):
        r = subprocess.run([sys.executable, "-m", "organlab", "sweep", str(SAMPLE), "--out", str(tmp_path / "o"), *argv],
                           capture_output=True, text=True, timeout=120, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)))
        assert r.returncode == 2 and what in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert main(["batch", str(tmp_path / "none"), "--out", str(tmp_path / "o"), "--workers", "0", "--quiet"]) == 2


def test_packed_silhouettes_come_back_bit_for_bit_and_eight_times_smaller():
    from organlab.batch._task import PackedSilhouettes
    from organlab.masks import Silhouette

    rng = np.random.default_rng(3)
    sils = []
    for shape in ((48, 64), (37, 51)):  # views of two sizes, one not a multiple of 8 pixels
        cov = np.zeros(shape, np.float32)
        cov[10:30, 12:40] = 1.0
        edge = (slice(9, 31), 11)
        cov[edge] = rng.random(22, dtype=np.float32)
        cov[0, 0], cov[0, 1], cov[1, 0] = -0.0, np.nan, 1e-45  # bits that a value comparison would lose
        sils.append(Silhouette(cov > 0.5, cov, 17.5, "subtraction", {"reason": "test"}))
    packed = PackedSilhouettes(sils)
    back = pickle.loads(pickle.dumps(packed, protocol=5)).unpack()
    for a, b in zip(sils, back):
        assert b.mask.dtype == bool and np.array_equal(a.mask, b.mask)
        assert b.coverage.dtype == np.float32 and np.array_equal(a.coverage.view(np.uint32), b.coverage.view(np.uint32))
        assert (b.threshold, b.source, b.info) == (a.threshold, a.source, a.info)
    raw = sum(s.mask.nbytes + s.coverage.nbytes for s in sils)
    # a bit per pixel twice plus 8 bytes per fractional pixel: 15x smaller here (18x on the sample's views)
    assert packed.nbytes < raw / 8
    from dask.sizeof import sizeof

    assert sizeof(packed) == packed.nbytes  # what Dask counts when it weighs sending a prefix's result


def test_shared_first_stages_are_a_task_of_their_own():
    # a threshold with one carving (hull and coloring at one voxel size): the carving is shared too, a task per method
    one = ob.plan_leaves(ob.plan_tasks(ob.expand({"threshold": [10.0, 35.0], "method": ["hull", "coloring"]})))
    assert [(until, [[s.method for s in t] for t in tasks]) for until, tasks in one] == [
        ("carving", [["hull"], ["coloring"]]), ("carving", [["hull"], ["coloring"]])]
    # several carvings per threshold: calibration, silhouettes and poses shared, a task per carving
    two = ob.plan_leaves(ob.plan_tasks(ob.expand({"threshold": [10.0], "voxel_size": [2.0, 1.0],
                                                  "method": ["hull", "coloring"]})), n_workers=2)
    assert [until for until, _ in two] == ["poses"] and [len(t) for t in two[0][1]] == [2, 2]
    # fewer tasks than workers: a task per setting
    four = ob.plan_leaves(ob.plan_tasks(ob.expand({"threshold": [10.0], "voxel_size": [2.0, 1.0],
                                                   "method": ["hull", "coloring"]})), n_workers=4)
    assert [len(t) for t in four[0][1]] == [1, 1, 1, 1]
    # a lone setting runs its stages itself
    assert ob.plan_leaves([[ob.Settings()]]) == [(None, [[ob.Settings()]])]
