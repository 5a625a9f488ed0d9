"""One task of a sweep or a batch: a group of settings of one session through one Engine.

The same function runs in a Dask worker process and in the serial fallback.
Its input is a :class:`Prepared` session (loaded, calibrated and its view
images decoded once, by the client) and plain settings dictionaries; its
output is plain data (the report and, when asked, the bytes of the result
files), so nothing but Dask's own wire format crosses between processes and
nothing is read back from a pickle on disk.
"""

from __future__ import annotations

import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from ..calibration import Calibration
from ..engine import STAGES, Engine, Settings
from ..errors import OrganlabError
from ..session import Session, load_session

__all__ = ["Prepared", "prepare", "run_task"]


@dataclass(frozen=True)
class Prepared:
    """A session ready to reconstruct, as sent to the workers.

    Attributes
    ----------
    session : Session
        Loaded and validated (paths absolute, as seen by the client).
    calibration : dict
        The calibration's ``calibration.json`` content (:meth:`Calibration.to_dict`): data, not an object.
    how : str
        Where the calibration came from (``calibration_for``'s second value).
    images : tuple of (H, W, 3) uint8
        The views' images, decoded once.
    """

    session: Session
    calibration: dict
    how: str
    images: tuple

    @property
    def nbytes(self):
        return int(sum(im.nbytes for im in self.images))


def prepare(session, *, calibration=None, recalibrate=False, settings=None):
    """Load, calibrate and read a session once, on the client (the engine's calibration stage).

    ``settings``: the first a task will run (its grid is checked against the
    memory before the calibration runs).  Raises the session's own one-line
    errors (:class:`~organlab.errors.OrganlabError`).
    """
    engine = Engine(session, calibration=calibration, recalibrate=recalibrate)
    stages = {}
    engine.run(settings or Settings(), until="calibration", on_stage=lambda name, result: stages.setdefault(name, result))
    cal = stages["calibration"]
    return Prepared(engine.session, cal.calibration.to_dict(), cal.how, tuple(engine.images))


@contextmanager
def _one_thread():
    """numba's parallel loops on one thread while a task runs, wherever it runs.

    A task's result then does not depend on where it ran: numba's loops round
    differently with other thread counts (the float32 hull field differs by
    1 ulp between 1 and 2 threads, measured on the sample), and a worker runs
    one task at a time on one core anyway (the LocalCluster also sets
    ``NUMBA_NUM_THREADS=1`` before its workers start).
    """
    import numba

    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(before)


def _worker_memory():
    """The memory limit of the Dask worker running this task, bytes (None outside a worker, or without a limit).

    The engine's pre-flight check then refuses a grid that does not fit in one
    worker's share rather than the machine's.
    """
    try:
        from distributed import get_worker

        return get_worker().memory_manager.memory_limit or None
    except (ImportError, ValueError, AttributeError):
        return None


def _report_dict(rec):
    rep = rec.report
    return rep.to_dict() if hasattr(rep, "to_dict") else dict(rep)


def _files_of(rec):
    """The result's files (:meth:`Reconstruction.save`), written in a local temporary folder and returned as bytes."""
    with tempfile.TemporaryDirectory(prefix="organlab-task-") as tmp:
        rec.save(tmp, atomic=False)
        return {p.name: p.read_bytes() for p in sorted(Path(tmp).iterdir()) if p.is_file()}


def run_task(prepared, settings, *, files=True):
    """Reconstruct ``prepared`` at each of ``settings``, in order, through one Engine.

    Parameters
    ----------
    prepared : Prepared
    settings : list of dict
        :meth:`Settings.to_dict` forms.
    files : bool
        Return the result files' bytes (``report.json``, ``voxels.npz``,
        ``mesh.ply``, ``mesh.stl``, ``calibration.json``).

    Returns
    -------
    list of dict
        Per setting: ``settings`` (dict), ``report`` (dict or None),
        ``files`` (dict of name -> bytes, or None), ``seconds`` (wall time
        of this setting, shared stages counted where they ran),
        ``stages_run`` (the stages computed for it; the others were kept
        from the setting before), ``error``
        (one line, or None).  A setting that fails with an organlab error
        (bad input, nothing carved) is an error entry; the others still run.
    """
    with _one_thread():
        return _run(prepared, settings, files)


def _run(prepared, settings, files):
    session = prepared.session
    cal = Calibration.from_dict(prepared.calibration, image_size=session.image_size, where=f"{session.root} (calibration)")
    engine = Engine(session, calibration=cal, images=list(prepared.images), max_memory=_worker_memory())
    out = []
    for d in settings:
        t0 = time.perf_counter()
        entry = {"settings": dict(d), "report": None, "files": None, "seconds": 0.0, "error": None}
        before = dict(engine.computed)
        try:
            rec = engine.run(Settings.from_dict(d))
            entry["stages_run"] = [k for k in STAGES if engine.computed[k] > before[k]]
            entry["report"] = _report_dict(rec)
            if files:
                entry["files"] = _files_of(rec)
        except (OrganlabError, ValueError) as e:
            entry["error"] = str(e).splitlines()[0] if str(e) else type(e).__name__
        entry["seconds"] = time.perf_counter() - t0
        out.append(entry)
    return out
