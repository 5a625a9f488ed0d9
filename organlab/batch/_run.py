"""Running tasks: on a Dask cluster (local worker processes or a lab's scheduler), or in this process.

The client prepares each session once (:func:`~organlab.batch._task.prepare`),
scatters it to the workers once, submits one task per group of settings and
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
WORKER_CONFIG = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}

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
        meta = {"session": str(session_root), "settings": _json_round(entry["settings"]), "seconds": entry["seconds"]}
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
    import logging

    import dask

    n = workers if workers is not None else (os.cpu_count() or 1)
    # the nannies read their environment now, and keep it for the workers they restart
    with dask.config.set(WORKER_CONFIG):
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1", scheduler_port=0,
                               dashboard_address=None, env=dict(WORKER_ENV), silence_logs=logging.ERROR,
                               # the scheduler's HTTP routes (health, metrics) on a free port of 127.0.0.1, not :8787
                               scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
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
    return [{"settings": s.to_dict(), "report": None, "files": None, "seconds": 0.0, "error": message} for s in job.settings]


def execute(jobs, *, client, files, on_result):
    """Run every job, calling ``on_result(job, entries)`` on the client as each completes.

    A job whose preparation raises an organlab error, or whose task fails
    (a bug, a worker lost too often), gives error entries: the other jobs go on.
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
    from dask.distributed import as_completed

    client.register_plugin(worker_plugin(), name="organlab-start-libraries")
    scattered, futures = {}, as_completed()
    pending, prefixes, users = {}, {}, {}
    for i, job in enumerate(jobs):
        try:
            if job.key not in scattered:
                prep = job.prepare()
                [scattered[job.key]] = client.scatter([prep], broadcast=True, hash=False)
        except OrganlabError as e:
            on_result(job, _error_entries(job, str(e)))
            continue
        kept = None
        if shared.get((job.key, job.group), 0) > 1:
            g = job.key, job.group
            if g not in prefixes:  # before every job: the shared stages (their cost is unknown) start first
                prefixes[g] = client.submit(run_prefix, scattered[job.key], job.settings[0].to_dict(), until=job.until,
                                            pure=False,
                                            priority=2 * len(jobs) - i, key=f"organlab-prefix-{i}-{uuid.uuid4().hex}")
            kept = prefixes[g]
            users[g] = users.get(g, 0) + 1
        f = client.submit(run_task, scattered[job.key], [s.to_dict() for s in job.settings], files=files, kept=kept,
                          first=job.first, pure=False, priority=len(jobs) - i,
                          key=f"organlab-task-{i}-{uuid.uuid4().hex}")
        pending[f.key] = job
        futures.add(f)
    for f in futures:
        job = pending.pop(f.key)
        g = job.key, job.group
        if g in users:
            users[g] -= 1
            if users[g] == 0:  # every task of the group is back: its shared stages can go
                prefixes.pop(g).release()
        try:
            entries = f.result()
        except OrganlabError as e:
            entries = _error_entries(job, str(e))
        except Exception as e:  # the task's own failure (or a worker lost too often): its settings fail, not the sweep
            text = str(e).splitlines()[0] if str(e) else ""
            entries = _error_entries(job, f"task failed: {type(e).__name__}: {text}")
            print(f"organlab: warning: {job.label}: task failed: {type(e).__name__}: {text}", file=sys.stderr)
        on_result(job, entries)
        f.release()
