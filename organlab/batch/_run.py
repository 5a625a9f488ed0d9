"""Running tasks: on a Dask cluster (local worker processes or a lab's scheduler), or in this process.

The client prepares each session once (:func:`~organlab.batch._task.prepare`),
scatters it to the workers once, hands out the tasks (shared first stages,
then the settings that go on from them) one per free worker thread, and
writes each result it gets back into its own folder atomically.  A worker
that dies takes its task with it; the scheduler runs it again on another
worker (``distributed.scheduler.allowed-failures`` times); the results that
task had not returned yet are recomputed, the ones already written are not.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import uuid
from contextlib import contextmanager
from pathlib import Path

from ..errors import OrganlabError
from ..preflight import atomic_output_dir
from ._plan import _cost
from ._task import run_prefix, run_task

__all__ = ["Job", "execute", "dask_client", "finished", "write_result", "clean_partial", "start_libraries", "worker_plugin"]

#: Set in every worker process of the LocalCluster before it starts: one thread per library,
#: since each worker runs one task at a time on one core.
WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

#: Dask configuration the LocalCluster's nannies start their workers with: glibc's malloc left as in any
#: process.  Dask's nanny sets ``MALLOC_TRIM_THRESHOLD_=65536`` in its workers by default, to hand freed memory
#: back to the system at once; setting it also stops glibc from raising its mmap threshold, so every array of
#: more than 128 kB was mapped, zeroed by the kernel and unmapped again.  On the sample at 2 mm the colouring
#: stage took 4.7 s CPU in a worker (1.6 s of it in the kernel) against 2.5-3.1 s in this process; without the
#: variable 3.0-3.4 s (0.1-0.2 s in the kernel), measured in one idle worker.
#: Nor do the workers run Dask's statistical profiler (a thread sampling the task's stack every 10 ms, for the
#: dashboard, which the LocalCluster does not start), and the cluster's periodic checks run less often: the
#: event loops' health tick every 1 s (Dask: 20 ms, in the scheduler, each nanny and each worker), the nannies'
#: memory check every 0.5 s (0.1 s) and the system monitor every 2 s (0.5 s).  An idle cluster of 2 workers
#: then took 0.17 s CPU in this process and 0.07 s in each worker over 20 s, against 0.73-0.91 s and 0.34-0.40 s
#: with Dask's defaults (measured under load 13): about 1 s of a 20 s sweep's CPU, on cores the tasks need.
WORKER_CONFIG = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
                 "distributed.worker.profile.enabled": False,
                 "distributed.admin.tick.interval": "1s",
                 "distributed.worker.memory.monitor-interval": "500ms",
                 "distributed.admin.system-monitor.interval": "2s"}

SWEEP_FILE = "sweep.json"  # in each result folder: the settings and session it was computed for


class Job:
    """One task to run: a prepared session (or the error that prevented it), settings and their folder names."""

    def __init__(self, key, prepare, settings, names, *, label, group=None, first=True, until=None):
        self.key = key  # the session's key (several jobs of one session share its scatter)
        self.prepare = prepare  # () -> Prepared, called once per key on the client
        self.settings = settings  # list of Settings
        self.names = names  # folder name of each setting
        self.label = label  # the session's name, for the rows
        self.group = group  # jobs of one session with the same group share their first stages (run_prefix)
        self.first = first  # the group's first job: its first entry counts the shared stages
        self.until = until  # the last stage the group's jobs share


def finished(folder, settings_dict, session_root):
    """True when ``folder`` holds a complete result of these settings for this session."""
    meta = Path(folder) / SWEEP_FILE
    if not (meta.is_file() and (Path(folder) / "report.json").is_file()):
        return False
    try:
        doc = json.loads(meta.read_text())
    except (OSError, ValueError):
        return False
    return doc.get("settings") == _json_round(settings_dict) and doc.get("session") == str(session_root)


def _json_round(d):
    return json.loads(json.dumps(d, default=list))


def write_result(folder, entry, session_root):
    """Write one result's files into ``folder`` atomically (a temporary folder renamed into place)."""
    folder = Path(folder)
    if folder.exists() and not finished(folder, entry["settings"], session_root) and (folder / SWEEP_FILE).exists():
        shutil.rmtree(folder)  # a result of other settings under this name (written by an older organlab): replaced
    with atomic_output_dir(folder) as tmp:
        for name, data in entry["files"].items():
            (tmp / name).write_bytes(data)
        meta = {"session": str(session_root), "settings": _json_round(entry["settings"]), "seconds": entry["seconds"],
                "cpu_seconds": entry.get("cpu_seconds")}
        (tmp / SWEEP_FILE).write_text(json.dumps(meta, indent=1) + "\n")


def clean_partial(root):
    """Remove the temporary folders an interrupted run left in ``root`` (``.NAME.tmp-*``, ``.NAME.old-*``)."""
    root = Path(root)
    if not root.is_dir():
        return []
    gone = []
    for p in root.iterdir():
        if p.is_dir() and p.name.startswith(".") and (".tmp-" in p.name or ".old-" in p.name):
            shutil.rmtree(p, ignore_errors=True)
            gone.append(p)
    return gone


@contextmanager
def dask_client(*, client=None, scheduler=None, workers=None):
    """A Dask client: the one given, one connected to ``scheduler``, or a LocalCluster of ``workers`` processes.

    The LocalCluster binds to 127.0.0.1 only, without a dashboard; each worker
    has one thread and :data:`WORKER_ENV`.  Yields None for the serial
    fallback (``workers=0`` and no scheduler).
    """
    if client is not None:
        yield client
        return
    scheduler = scheduler or os.environ.get("DASK_SCHEDULER_ADDRESS") or None
    if scheduler is None and workers == 0:
        yield None
        return
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:  # pragma: no cover - dask is pinned in environment.txt
        raise OrganlabError("dask.distributed is not installed: pip install -r environment.txt, or use --workers 0") from None
    if scheduler is not None:
        try:
            c = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as e:
            raise OrganlabError(f"cannot reach the Dask scheduler at {scheduler} ({e}); check --scheduler / "
                                "DASK_SCHEDULER_ADDRESS, or run locally without them") from None
        try:
            yield c
        finally:
            c.close()
        return
    import copy
    import logging

    import dask

    n = workers if workers is not None else (os.cpu_count() or 1)
    with dask.config.set(WORKER_CONFIG):
        # the nannies read their environment now and keep it for the workers they restart; their workers'
        # configuration is given as a copy (a nanny keeps a reference to the live one, which the context restores)
        config = {"distributed": copy.deepcopy(dask.config.get("distributed"))}
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1", scheduler_port=0,
                               dashboard_address=None, env=dict(WORKER_ENV), silence_logs=logging.ERROR,
                               # the scheduler's HTTP routes (health, metrics) on a free port of 127.0.0.1, not :8787
                               scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}, config=config)
        c = Client(cluster)
    try:
        yield c
    finally:
        c.close()
        cluster.close()


def start_libraries():
    """Load the native libraries a task needs in the calling thread: numba's thread pool, then pymeshlab.

    Run in each worker's main thread as it starts (:func:`worker_plugin`).
    A worker runs its tasks in a thread of its own, which ends when the
    worker closes; pymeshlab (with its bundled libtbb) first loaded in such a
    thread corrupts the heap when that thread or the process ends: glibc
    printed ``malloc_consolidate(): unaligned fastbin chunk detected`` as the
    cluster's workers closed, after every result was back (the viewer's worker
    thread had the same abort, organlab/viewer/_app.py).  numba's threads
    start first, so that its threading layer is chosen before pymeshlab's
    libtbb is loaded.
    """
    import numba

    numba.get_num_threads()  # starts numba's thread pool (its threading layer is chosen now)
    try:
        import pymeshlab  # noqa: F401
    except ImportError:  # pragma: no cover - pymeshlab is pinned; without it finishing says so in the task
        pass


def worker_plugin():
    """A ``distributed.WorkerPlugin`` running :func:`start_libraries` as each worker starts (restarted ones too)."""
    from distributed import WorkerPlugin

    class StartLibraries(WorkerPlugin):
        name = "organlab-start-libraries"

        def setup(self, worker):  # in the worker's event loop: its main thread
            start_libraries()

    return StartLibraries()


def worker_memory(client):
    """Memory limit of the smallest worker, bytes (None when the workers set none)."""
    if client is None:
        return None
    limits = [w.get("memory_limit") or 0 for w in client.scheduler_info(n_workers=-1)["workers"].values()]
    limits = [m for m in limits if m > 0]
    return min(limits) if limits else None


def n_workers(client):
    return 1 if client is None else max(1, len(client.scheduler_info(n_workers=-1)["workers"]))


def _error_entries(job, message):
    return [{"settings": s.to_dict(), "report": None, "files": None, "seconds": 0.0, "cpu_seconds": 0.0, "error": message}
            for s in job.settings]


#: Shared first stages computed ahead of the tasks that go on from them, per worker thread: their results
#: (a threshold's packed silhouettes, poses and carving) wait on the workers until those tasks ran.
OPEN_PREFIXES_PER_THREAD = 3


def execute(jobs, *, client, files, on_result):
    """Run every job, calling ``on_result(job, entries)`` on the client as each completes.

    A job whose preparation raises an organlab error, or whose task fails
    (a bug, a worker lost too often), gives error entries: the other jobs go on.

    On a cluster the client hands out the work itself, one task per free
    worker thread (:func:`_distributed`): the shared first stages first
    (their cost is not known before), then the largest tasks.
    """
    shared = {}  # (session key, group) -> number of jobs: a group of one runs its first stages itself
    for job in jobs:
        if job.group is not None and job.until is not None:
            shared[job.key, job.group] = shared.get((job.key, job.group), 0) + 1
    if client is None:
        prepared, prefixes = {}, {}
        for job in jobs:
            try:
                if job.key not in prepared:
                    prepared[job.key] = job.prepare()
                kept = None
                if shared.get((job.key, job.group), 0) > 1:
                    if (job.key, job.group) not in prefixes:
                        prefixes[job.key, job.group] = run_prefix(prepared[job.key], job.settings[0].to_dict(),
                                                                  until=job.until)
                    kept = prefixes[job.key, job.group]
                entries = run_task(prepared[job.key], [s.to_dict() for s in job.settings], files=files, kept=kept,
                                   first=job.first)
            except OrganlabError as e:
                entries = _error_entries(job, str(e))
            on_result(job, entries)
        return
    _distributed(jobs, {g for g, n in shared.items() if n > 1}, client, files, on_result)


def _failure(job, e):
    text = str(e).splitlines()[0] if str(e) else ""
    print(f"organlab: warning: {job.label}: task failed: {type(e).__name__}: {text}", file=sys.stderr)
    return f"task failed: {type(e).__name__}: {text}"


def _distributed(jobs, shared, client, files, on_result):
    """:func:`execute` on a Dask cluster: list scheduling by the client.

    At most one task per worker thread is on the cluster at a time: when one
    finishes, the next goes to the thread it freed.  The next is the first
    shared-prefix task not started (a threshold's silhouettes, poses and,
    when shared, carving: :func:`run_prefix`), while fewer than
    :data:`OPEN_PREFIXES_PER_THREAD` per thread wait for their tasks, else
    the largest task ready (its prefix done; ``_plan._cost``).  Unknown costs
    (the pose fit runs at some thresholds only) then come first and the end
    is made of the smallest tasks, so no worker idles long at the end; Dask's
    own queue had held the prefixes back behind the tasks already placed on
    the workers.  A prefix's result stays on its worker (its silhouettes
    packed: :class:`~organlab.batch._task.PackedSilhouettes`) and is sent to
    the other worker only when that one is free first.  A task lost with its
    worker is run again by the scheduler, a lost prefix result recomputed.
    Each session is prepared on the client once, just before its first task
    (the next session while the workers compute), scattered to every worker
    and released when its last task is back.
    """
    from dask.distributed import as_completed

    client.register_plugin(worker_plugin(), name="organlab-start-libraries")
    order = {id(job): i for i, job in enumerate(jobs)}
    left = {}  # session key -> jobs not back yet
    for job in jobs:
        left[job.key] = left.get(job.key, 0) + 1
    sessions = {}  # session key -> scattered Prepared future, or the error line of its preparation
    groups = {}  # (session key, group) -> {"jobs": [...], "future": prefix future or None, "left": n, "started": bool}
    prefix_queue, ready = [], []
    for job in jobs:
        g = job.key, job.group
        if g in shared:
            if g not in groups:
                groups[g] = {"jobs": [], "future": None, "left": 0, "started": False}
                prefix_queue.append(g)
            groups[g]["jobs"].append(job)
            groups[g]["left"] += 1
        else:
            ready.append(job)
    cost = {id(job): sum(map(_cost, job.settings)) for job in jobs}
    in_flight = {}  # future key -> ("prefix", group) or ("job", job)
    futures = as_completed()

    def session(key, prepare):
        if key not in sessions:
            try:
                [sessions[key]] = client.scatter([prepare()], broadcast=True, hash=False)
            except OrganlabError as e:
                sessions[key] = str(e)
        return sessions[key]

    def finish(job, entries):
        on_result(job, entries)
        left[job.key] -= 1
        if left[job.key] == 0 and not isinstance(sessions.get(job.key, ""), str):
            sessions.pop(job.key).release()  # every task of this session is back
        g = job.key, job.group
        if g in groups:
            grp = groups[g]
            grp["left"] -= 1
            if grp["left"] == 0 and grp["future"] is not None:
                grp["future"].release()  # the shared stages' result is no longer needed
                grp["future"] = None

    def next_item(capacity):
        n_open = sum(1 for g in groups.values() if g["started"] and g["left"] > 0)
        if prefix_queue and (n_open < OPEN_PREFIXES_PER_THREAD * capacity or not ready):
            return "prefix", prefix_queue[0]
        if ready:
            return "job", min(ready, key=lambda j: (-cost[id(j)], order[id(j)]))
        return None

    def start(kind, x):
        done = []  # (job, entries) of jobs that could not start
        if kind == "prefix":
            prefix_queue.remove(x)
            grp = groups[x]
            grp["started"] = True
            first = grp["jobs"][0]
            prep = session(first.key, first.prepare)
            if isinstance(prep, str):
                done += [(job, _error_entries(job, prep)) for job in grp["jobs"]]
            else:
                f = client.submit(run_prefix, prep, first.settings[0].to_dict(), until=first.until, pure=False,
                                  key=f"organlab-prefix-{order[id(first)]}-{uuid.uuid4().hex}")
                grp["future"] = f
                in_flight[f.key] = ("prefix", x)
                futures.add(f)
        else:
            ready.remove(x)
            prep = session(x.key, x.prepare)
            if isinstance(prep, str):
                done.append((x, _error_entries(x, prep)))
            else:
                grp = groups.get((x.key, x.group))
                f = client.submit(run_task, prep, [s.to_dict() for s in x.settings], files=files,
                                  kept=None if grp is None else grp["future"], first=x.first, pure=False,
                                  key=f"organlab-task-{order[id(x)]}-{uuid.uuid4().hex}")
                in_flight[f.key] = ("job", x)
                futures.add(f)
        return done

    def fill():
        capacity = max(1, sum(client.nthreads().values()))
        done = []
        while len(in_flight) < capacity:
            item = next_item(capacity)
            if item is None:
                break
            done += start(*item)
        # the next session prepared while the workers compute (a batch's load and calibration)
        upcoming = next_item(capacity)
        if upcoming is not None:
            job = groups[upcoming[1]]["jobs"][0] if upcoming[0] == "prefix" else upcoming[1]
            session(job.key, job.prepare)
        for job, entries in done:
            finish(job, entries)
        return bool(done)

    while fill() or in_flight:
        if not in_flight:
            continue
        f = next(futures)
        kind, x = in_flight.pop(f.key)
        if kind == "prefix":
            grp = groups[x]
            if f.status == "finished":
                ready.extend(grp["jobs"])  # the tasks that go on from it
            else:
                why = _failure(grp["jobs"][0], f.exception())
                grp["future"] = None
                f.release()
                for job in grp["jobs"]:
                    finish(job, _error_entries(job, why))
            continue
        fill()  # the freed thread gets its next task before this result is fetched and written
        try:
            entries = f.result()
        except OrganlabError as e:
            entries = _error_entries(x, str(e))
        except Exception as e:  # the task's own failure (or a worker lost too often): its settings fail, not the sweep
            entries = _error_entries(x, _failure(x, e))
        f.release()
        finish(x, entries)
