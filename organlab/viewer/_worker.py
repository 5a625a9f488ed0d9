"""A single worker thread that runs the newest request and cancels older ones."""

from __future__ import annotations

import threading
import traceback

from ..engine import Cancelled  # raised inside a job (by check(), or by the engine's cancel) when a newer request arrived

__all__ = ["Cancelled", "LatestWorker"]


class LatestWorker:
    """Run ``job(generation, request, check)`` for the newest request only.

    ``submit`` bumps a generation counter; a running job calls ``check()``
    between its steps, which raises :class:`Cancelled` once a newer request
    is pending, so an older computation stops early and the newest runs next.
    """

    def __init__(self, job, *, on_error=None):
        self._job = job
        self._on_error = on_error
        self._cv = threading.Condition()
        self._pending = None
        self.generation = 0  # newest request
        self.finished = 0  # generation of the last job that completed
        self.cancelled = 0  # number of jobs cancelled by a newer request
        self.running = False
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="organlab-viewer-worker", daemon=True)
        self._thread.start()

    def submit(self, request):
        """Queue a request; returns its generation."""
        with self._cv:
            self.generation += 1
            self._pending = (self.generation, request)
            self._cv.notify_all()
            return self.generation

    def stale(self, generation: int) -> bool:
        """Whether a newer request arrived (or the worker stops): the engine's ``cancel()`` of a job."""
        return self._stop or generation != self.generation

    def check(self, generation: int) -> None:
        """Raise :class:`Cancelled` when :meth:`stale`."""
        if self.stale(generation):
            raise Cancelled

    def wait(self, generation=None, timeout=60.0):
        """Block until ``generation`` (default: the newest) finished; True if it did."""
        with self._cv:
            g = self.generation if generation is None else generation
            return self._cv.wait_for(lambda: self.finished >= g or self._stop, timeout)

    def stop(self):
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        self._thread.join(timeout=30)

    def _run(self):
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._pending is not None or self._stop)
                if self._stop:
                    return
                gen, req = self._pending
                self._pending = None
                self.running = True
            try:
                self._job(gen, req, lambda: self.check(gen))
                done = True
            except Cancelled:
                done = False
                self.cancelled += 1
            except Exception as e:  # shown in the GUI; the worker keeps serving
                done = True
                if self._on_error is not None:
                    self._on_error(e, traceback.format_exc())
                else:
                    traceback.print_exc()
            with self._cv:
                self.running = False
                if done:
                    self.finished = max(self.finished, gen)
                self._cv.notify_all()
