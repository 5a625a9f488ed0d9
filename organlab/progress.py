"""A tiny text progress bar for the command line (no dependency)."""

from __future__ import annotations

import sys
import time


class ProgressBar:
    """Progress of one stage, drawn on ``stream`` (stderr).

    Call it as ``bar(done, total)``; :meth:`close` prints the final line with
    the elapsed time.  On a terminal the bar redraws in place; elsewhere only
    the final line is written, so logs stay short.
    """

    def __init__(self, label, *, stream=None, width=28):
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.t0 = time.perf_counter()
        self.done = 0
        self.total = 0
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()

    def __call__(self, done, total):
        self.done, self.total = done, total
        if self.tty:
            self._draw("\r")

    def _draw(self, lead, end=""):
        frac = self.done / self.total if self.total else 1.0
        n = int(round(frac * self.width))
        bar = "#" * n + "-" * (self.width - n)
        elapsed = time.perf_counter() - self.t0
        self.stream.write(f"{lead}{self.label:<12} [{bar}] {self.done}/{self.total} {elapsed:6.2f} s{end}")
        self.stream.flush()

    def close(self):
        if self.total == 0:
            self.done = self.total = 1
        self._draw("\r" if self.tty else "", "\n")


class NullProgress:
    def __call__(self, done, total):
        pass

    def close(self):
        pass
