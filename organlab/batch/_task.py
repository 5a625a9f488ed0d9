"""One task of a sweep or a batch: a group of settings of one session through one Engine.

The same function runs in a Dask worker process and in the serial fallback.
Its input is a :class:`Prepared` session (loaded, calibrated and its view
images decoded once, by the client) and plain settings dictionaries; its
output is plain data (the report and, when asked, the bytes of the result
files), so nothing but Dask's own wire format crosses between processes and
nothing is read back from a pickle on disk.
"""

from __future__ import annotations

import os
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..calibration import Calibration
from ..engine import STAGES, Engine, Settings
from ..errors import OrganlabError
from ..masks import Silhouette
from ..session import Session, load_session

__all__ = ["Prepared", "prepare", "run_prefix", "run_task", "PREFIX_UNTIL", "PackedSilhouettes"]

#: The stages a sweep's settings sharing a threshold share (calibration, silhouettes, poses): one task
#: computes them, the tasks that carve at that threshold go on from its result (:meth:`Engine.kept`).
PREFIX_UNTIL = "poses"


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


def _cpu():
    """CPU time (user + sys) of this process, every thread, s: a task's, in a worker that runs one at a time."""
    t = os.times()
    return t.user + t.system


_ONE = np.float32(1.0).view(np.uint32)


class PackedSilhouettes:
    """A list of :class:`~organlab.masks.Silhouette`, packed to send between processes, unpacked bit for bit.

    A view's mask and the pixels of its coverage that are exactly 1 as bits
    (``np.packbits``), the other non-zero coverages as (index, value) pairs:
    the sample's 36 views at 640 x 480 (a bool mask and a float32 coverage
    each, 55.3 MB) pack into 3.1 MB, so the silhouettes a threshold's
    shared first stages computed cost little to send to the worker that
    goes on from them (:func:`run_prefix`, :func:`run_task`).  Exact: the
    coverage is compared by its bits, so -0.0 or NaN come back as they were.

    Examples
    --------
    >>> import numpy as np
    >>> from organlab.masks import Silhouette
    >>> cov = np.array([[0, 0.25, 1], [1, 1, 0]], np.float32)
    >>> s = Silhouette(cov > 0.5, cov, 20.0, "subtraction")
    >>> [back] = PackedSilhouettes([s]).unpack()
    >>> np.array_equal(back.mask, s.mask), np.array_equal(back.coverage, s.coverage), back.threshold
    (True, True, 20.0)
    """

    def __init__(self, silhouettes):
        self.views = []
        for sil in silhouettes:
            mask = np.ascontiguousarray(sil.mask, dtype=bool)
            cov = np.ascontiguousarray(sil.coverage, dtype=np.float32)
            bits = cov.reshape(-1).view(np.uint32)
            one = bits == _ONE
            other = np.flatnonzero((bits != 0) & ~one).astype(np.int64 if bits.size > 2**31 - 1 else np.int32)
            self.views.append((mask.shape, np.packbits(mask.reshape(-1)), cov.shape, np.packbits(one), other,
                               cov.reshape(-1)[other], sil.threshold, sil.source, sil.info))

    @property
    def nbytes(self):
        return int(sum(v[1].nbytes + v[3].nbytes + v[4].nbytes + v[5].nbytes for v in self.views))

    def unpack(self):
        out = []
        for mshape, mbits, cshape, onebits, other, values, threshold, source, info in self.views:
            n = int(np.prod(mshape))
            mask = np.unpackbits(mbits, count=n).view(bool).reshape(mshape)
            size = int(np.prod(cshape))
            cov = np.unpackbits(onebits, count=size).astype(np.float32)  # the ones (and +0.0 elsewhere)
            cov[other] = values
            out.append(Silhouette(mask, cov.reshape(cshape), threshold, source, info))
        return out


def _pack(kept):
    """:meth:`Engine.kept`'s silhouettes packed (:class:`PackedSilhouettes`), the rest as it is."""
    if "silhouettes" not in kept:
        return kept
    key, sils, seconds = kept["silhouettes"]
    return {**kept, "silhouettes": (key, PackedSilhouettes(sils), seconds)}


def _unpack(kept):
    if "silhouettes" not in kept or not isinstance(kept["silhouettes"][1], PackedSilhouettes):
        return kept
    key, packed, seconds = kept["silhouettes"]
    return {**kept, "silhouettes": (key, packed.unpack(), seconds)}


def _register_sizeof():
    """Tell Dask how big a packed kept result is (it counts an unknown object as a few bytes)."""
    try:
        from dask.sizeof import sizeof
    except ImportError:  # pragma: no cover - dask is pinned
        return
    sizeof.register(PackedSilhouettes)(lambda p: p.nbytes)


_register_sizeof()


def _report_dict(rec):
    rep = rec.report
    return rep.to_dict() if hasattr(rep, "to_dict") else dict(rep)


def _files_of(rec):
    """The result's files (:meth:`Reconstruction.save`), written in a local temporary folder and returned as bytes."""
    with tempfile.TemporaryDirectory(prefix="organlab-task-") as tmp:
        rec.save(tmp, atomic=False)
        return {p.name: p.read_bytes() for p in sorted(Path(tmp).iterdir()) if p.is_file()}


def _engine(prepared):
    session = prepared.session
    cal = Calibration.from_dict(prepared.calibration, image_size=session.image_size, where=f"{session.root} (calibration)")
    return Engine(session, calibration=cal, images=list(prepared.images), max_memory=_worker_memory())


def run_prefix(prepared, settings, *, until=PREFIX_UNTIL):
    """Run the stages up to ``until`` for ``settings`` (a dict), for the tasks that go on from them.

    Returns
    -------
    dict
        ``kept`` (:meth:`Engine.kept`, its silhouettes packed:
        :class:`PackedSilhouettes`; None after an error), ``stages_run``,
        ``seconds`` (wall time), ``cpu_seconds`` (CPU time of the process
        meanwhile), ``error`` (one line, or None): given to :func:`run_task`
        as its ``kept``.
    """
    with _one_thread():
        t0, c0 = time.perf_counter(), _cpu()
        engine = _engine(prepared)
        out = {"kept": None, "stages_run": [], "seconds": 0.0, "cpu_seconds": 0.0, "error": None}
        try:
            engine.run(Settings.from_dict(settings), until=until)
            out["kept"] = _pack(engine.kept(until))
            out["stages_run"] = [k for k in STAGES if engine.computed[k]]
        except (OrganlabError, ValueError) as e:
            out["error"] = str(e).splitlines()[0] if str(e) else type(e).__name__
        out["seconds"] = time.perf_counter() - t0
        out["cpu_seconds"] = _cpu() - c0
        return out


def run_task(prepared, settings, *, files=True, kept=None, first=True):
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
        ``cpu_seconds`` (the CPU time of the process meanwhile, counted the same way),
        ``stages_run`` (the stages computed for it; the others were kept
        from the setting before), ``error``
        (one line, or None).  A setting that fails with an organlab error
        (bad input, nothing carved) is an error entry; the others still run.
    kept : dict, optional
        What :func:`run_prefix` returned for these settings' first stages:
        they are taken, not recomputed (its error is every setting's error).
    first : bool
        With ``kept``: count the prefix's stages and time in the first
        setting's entry (one task of those sharing a prefix does).
    """
    with _one_thread():
        return _run(prepared, settings, files, kept, first)


def _run(prepared, settings, files, kept=None, first=True):
    if kept is not None and kept["error"] is not None:
        return [{"settings": dict(d), "report": None, "files": None, "seconds": 0.0, "cpu_seconds": 0.0,
                 "stages_run": [], "error": kept["error"]} for d in settings]
    t0, c0 = time.perf_counter(), _cpu()
    engine = _engine(prepared)
    if kept is not None:
        engine.keep(_unpack(kept["kept"]))
    out = []
    for i, d in enumerate(settings):
        if i:
            t0, c0 = time.perf_counter(), _cpu()
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
        entry["cpu_seconds"] = _cpu() - c0
        if kept is not None and first and i == 0:  # the shared stages, counted where they ran
            entry["stages_run"] = [k for k in STAGES if k in kept["stages_run"] or k in entry.get("stages_run", ())]
            entry["seconds"] += kept["seconds"]
            entry["cpu_seconds"] += kept.get("cpu_seconds", 0.0)
        out.append(entry)
    return out
