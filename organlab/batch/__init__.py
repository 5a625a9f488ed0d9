"""Many reconstructions at once: parameter sweeps of one session, batches of sessions, on Dask.

:func:`sweep` reconstructs one session at every combination of a grid of
settings; :func:`batch` reconstructs many sessions at one setting.  Both run
each group of settings as a task on a ``dask.distributed`` cluster — a
``LocalCluster`` of worker processes, or a lab's scheduler — or, without
one, in this process with the same code::

    import organlab as ol
    table = ol.sweep("sample_sessions/aaa_phantom", {"threshold": [10, 20, 30]},
                     settings=ol.batch.Settings(voxel_size=2.0))
    table[["threshold", "volume_mm3", "agreement_mean_iou"]]
    table.attrs["recommended"]["reason"]

Work is shared, not repeated: the client loads and calibrates a session and
decodes its images once and sends them to each worker once; settings that
differ only from the carving stage on (voxel size, method, colour
threshold, ...) share one computation of their silhouettes and poses (a
task of its own, whose result the tasks of each carving go on from, see
:func:`~organlab.batch._plan.plan_leaves`); settings sharing a carving run
in one task through one :class:`~organlab.engine.Engine`.  With ``out``, each result is
written atomically into its own folder named by its settings, a re-run
skips the finished ones, and the table (``summary.csv``), the recommended
setting (``recommended.json``) and the plots (``plots/*.png``) are written
beside them.  See ``docs/scale.md``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ..progress import NullProgress
from ..errors import OrganlabError
from ..preflight import available_memory, check_grid_memory
from ..engine import Settings
from ..session import Session, load_session
from ._plan import expand, parse_values, plan_leaves, plan_tasks, result_name
from ._run import SWEEP_FILE, Job, clean_partial, dask_client, execute, finished, n_workers, worker_memory, write_result
from ._table import SETTING_COLUMNS, plot_sweep, recommend, row_of
from ._task import prepare

__all__ = ["sweep", "batch", "recommend", "parse_values", "expand", "result_name", "plan_tasks", "plan_leaves", "dask_client", "Settings"]


def _root(session):
    return str((session.root if isinstance(session, Session) else Path(session)).resolve())


def _progress(progress, total):
    bar = progress if progress is not None else NullProgress()
    bar(0, total)
    return bar


def _finished_entry(folder, settings_dict):
    report = json.loads((folder / "report.json").read_text())
    meta = json.loads((folder / SWEEP_FILE).read_text())
    return {"settings": settings_dict, "report": report, "files": None, "seconds": meta.get("seconds", float("nan")),
            "cpu_seconds": float("nan") if meta.get("cpu_seconds") is None else meta["cpu_seconds"], "error": None, "status": "finished before"}


def _check_memory(session, settings, limit):
    """The pre-flight memory check of one task's grid against one worker's memory; the error line or None."""
    roi = settings.roi if getattr(settings, "roi", None) is not None else (session.roi_min, session.roi_max)
    try:
        check_grid_memory(roi[0], roi[1], settings.voxel_size, max_memory=limit, method=settings.method,
                          tolerance=settings.tolerance, where=str(session.json_path))
    except OrganlabError as e:
        return str(e)
    return None


def _table(rows):
    import pandas as pd

    df = pd.DataFrame(rows)
    for c in ("error", "warnings", "worst_view"):
        if c in df:
            df[c] = df[c].fillna("")
    return df


def _write_csv(df, path):
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    df.to_csv(tmp, index=False)
    os.replace(tmp, path)


def _as_settings(settings):
    if settings is None:
        return Settings()
    if isinstance(settings, dict):
        return Settings.from_dict(settings)
    return settings.validate()


def sweep(session: Session | str | Path, grid: dict[str, Any], *, settings: Settings | dict | None = None,
          out: str | Path | None = None, client: Any = None, workers: int | None = 0, scheduler: str | None = None,
          calibration: Any = None, recalibrate: bool = False, progress: Callable[[int, int], Any] | None = None,
          plots: bool = True) -> Any:
    """Reconstruct one session at every combination of a grid of settings.

    Parameters
    ----------
    session : Session or str or Path
    grid : dict of str -> list
        Setting (a :class:`Settings` field: ``'threshold'``, ``'voxel_size'``,
        ``'method'``, ``'color_threshold'``, ...) -> its values, e.g.
        ``{"threshold": [10, 20, 30], "voxel_size": [2.0, 1.0]}``; ``None`` is
        the automatic threshold.
    settings : Settings or dict, optional
        The settings not swept (default ``Settings()``).
    out : str or Path, optional
        Folder for ``results/NAME/`` (one per setting, see :func:`result_name`),
        ``summary.csv``, ``recommended.json`` and ``plots/``.  A re-run skips
        the results already there.  Default: nothing written.
    client : dask.distributed.Client, optional
        Run the tasks on this cluster.
    workers : int
        Without ``client`` or ``scheduler``: 0 runs every task in this process
        (no Dask); N > 0 starts a LocalCluster of N worker processes (one
        thread each, bound to 127.0.0.1, no dashboard) for this call.
    scheduler : str, optional
        Address of a running Dask scheduler (``tcp://host:8786``); default the
        ``DASK_SCHEDULER_ADDRESS`` environment variable when set.
    calibration : Calibration or str or Path, optional
        As in :func:`organlab.reconstruct`; computed once on the client otherwise.
    recalibrate : bool
    progress : callable(done, total), optional
        Called as results arrive (``organlab.progress.ProgressBar`` in the CLI).
    plots : bool
        With ``out``: write the PNG plots.

    Returns
    -------
    pandas.DataFrame
        One row per setting, in the grid's order (columns:
        :func:`organlab.batch._table.row_of`); ``attrs["recommended"]``: the
        recommended setting (:func:`recommend`), ``attrs["swept"]``: the
        settings that vary.

    Examples
    --------
    >>> import organlab as ol
    >>> t = ol.sweep("sample_sessions/aaa_phantom", {"threshold": [15.0, 20.0]},
    ...              settings={"voxel_size": 4.0, "finish": False})
    >>> list(t["threshold"]), bool((t["status"] == "done").all())
    ([15.0, 20.0], True)
    """
    if not isinstance(session, Session):
        session = load_session(session)
    base = _as_settings(settings)
    all_settings = expand(grid, base)
    swept = [c for c in grid if len({json.dumps(getattr(s, c), default=list) for s in all_settings}) > 1]
    names = [result_name(s) for s in all_settings]
    root = _root(session)
    results = None if out is None else Path(out) / "results"
    if out is not None:
        if Path(out).exists() and not Path(out).is_dir():
            raise OrganlabError(f"{out}: --out exists and is not a folder; give a folder path")
        results.mkdir(parents=True, exist_ok=True)
        clean_partial(results)
    rows = [None] * len(all_settings)
    index = {n: i for i, n in enumerate(names)}
    todo = []
    for i, (s, n) in enumerate(zip(all_settings, names)):
        if results is not None and finished(results / n, s.to_dict(), root):
            rows[i] = row_of(session.name, n, _finished_entry(results / n, s.to_dict()))
        else:
            todo.append(s)
    bar = _progress(progress, len(all_settings))
    done = [len(all_settings) - len(todo)]
    bar(done[0], len(all_settings))

    with dask_client(client=client, scheduler=scheduler, workers=workers) as c:
        limit = worker_memory(c) or available_memory()
        runnable = []
        for s in todo:
            why = _check_memory(session, s, limit)
            if why is None:
                runnable.append(s)
            else:
                i = index[result_name(s)]
                rows[i] = row_of(session.name, names[i], {"settings": s.to_dict(), "error": why})
                done[0] += 1
        prepared = {}

        def prep():
            if "p" not in prepared:
                prepared["p"] = prepare(session, calibration=calibration, recalibrate=recalibrate, settings=runnable[0])
            return prepared["p"]

        # one job per carving, or per setting (plan_leaves); the jobs of one threshold share its calibration,
        # silhouettes and poses (and its carving when it has one), computed once, by a task of their own
        groups = plan_leaves(plan_tasks(runnable), n_workers=0 if c is None else n_workers(c))
        jobs = [Job(root, prep, leaf, [result_name(s) for s in leaf], label=session.name, group=gi, first=li == 0,
                    until=until) for gi, (until, leaves) in enumerate(groups) for li, leaf in enumerate(leaves)]

        def on_result(job, entries):
            for name, entry in zip(job.names, entries):
                if results is not None and entry["files"] is not None:
                    write_result(results / name, entry, root)
                rows[index[name]] = row_of(session.name, name, entry)
                done[0] += 1
            bar(done[0], len(all_settings))

        execute(jobs, client=c, files=results is not None, on_result=on_result)
    bar.close()
    df = _table(rows)
    df.attrs["swept"] = swept
    df.attrs["recommended"] = rec = recommend(df)
    if out is not None:
        out = Path(out)
        _write_csv(df, out / "summary.csv")
        (out / "recommended.json").write_text(json.dumps(rec, indent=1, default=str) + "\n")
        if plots:
            df.attrs["plots"] = [str(p) for p in plot_sweep(df, swept or list(grid)[:1], out / "plots")]
    return df


def batch(sessions: Sequence[Session | str | Path], settings: Settings | dict | None = None, *, out: str | Path,
          client: Any = None, workers: int | None = 0, scheduler: str | None = None,
          progress: Callable[[int, int], Any] | None = None) -> Any:
    """Reconstruct many sessions at one setting.

    A session that cannot be loaded or reconstructed is one row with its
    error; the others go on.

    Parameters
    ----------
    sessions : list of (Session or str or Path)
    settings : Settings or dict, optional
    out : str or Path
        ``results/NAME/`` per session (``NAME`` its folder's name; ``-2``,
        ``-3`` ... when two share one) and ``summary.csv``.  A re-run skips
        the finished ones.
    client, workers, scheduler, progress
        As in :func:`sweep`.

    Returns
    -------
    pandas.DataFrame
        One row per session (``status`` ``'error'`` with ``error`` for a bad one).
    """
    s = _as_settings(settings)
    if not sessions:
        raise ValueError("sessions: give at least one session")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OrganlabError(f"{out}: --out exists and is not a folder; give a folder path")
    results = out / "results"
    results.mkdir(parents=True, exist_ok=True)
    clean_partial(results)
    names, seen = [], {}
    for x in sessions:
        base = (x.root if isinstance(x, Session) else Path(x)).resolve().name or "session"
        seen[base] = seen.get(base, 0) + 1
        names.append(base if seen[base] == 1 else f"{base}-{seen[base]}")
    rows = [None] * len(sessions)
    bar = _progress(progress, len(sessions))
    done = [0]
    jobs, index = [], {}
    for i, (x, name) in enumerate(zip(sessions, names)):
        root = _root(x)
        label = x.name if isinstance(x, Session) else Path(x).name
        if finished(results / name, s.to_dict(), root):
            rows[i] = row_of(label, name, _finished_entry(results / name, s.to_dict()))
            done[0] += 1
            continue

        def prep(x=x):
            session = x if isinstance(x, Session) else load_session(x)
            why = _check_memory(session, s, limit[0])
            if why is not None:
                raise OrganlabError(why)
            return prepare(session, settings=s)

        index[name] = i
        jobs.append(Job(root, prep, [s], [name], label=label))
    bar(done[0], len(sessions))
    limit = [None]
    with dask_client(client=client, scheduler=scheduler, workers=workers) as c:
        limit[0] = worker_memory(c) or available_memory()

        def on_result(job, entries):
            (entry,) = entries
            name = job.names[0]
            if entry["files"] is not None:
                write_result(results / name, entry, job.key)
            rows[index[name]] = row_of(job.label, name, entry)
            done[0] += 1
            bar(done[0], len(sessions))

        execute(jobs, client=c, files=True, on_result=on_result)
    bar.close()
    df = _table(rows)
    _write_csv(df, out / "summary.csv")
    return df
