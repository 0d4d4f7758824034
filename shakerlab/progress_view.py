"""The progress of a long command on stderr (reconstruct, diagnose, report, reprocess, demo).

A job's steps (``recon.progress``; ``workflows.progress_line`` connects them) are shown with their share of the whole job,
the elapsed time and an estimate of the time left. A heartbeat thread shows the current step again
while it runs, so a long step is never silent for more than a few seconds. On a terminal the line
is redrawn in place (``\\r``); otherwise (a log, a pipe) each update is one line. Nothing goes to
stdout, so ``--json`` output stays one JSON object; plain text only, no terminal escape codes.
"""
from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass

from shakerlab.words import duration_text

TTY_HEARTBEAT_S = 1.0       # a terminal line is redrawn this often
LOG_HEARTBEAT_S = 3.0       # a log gets a line this often while a step runs (the promise: never 5 s silent)


class ProgressLine:
    """Shows :class:`Status` (or ``recon.progress.Update``) objects on ``stream``; :meth:`note` adds a line of its own."""

    def __init__(self, stream=None, heartbeat_s: float | None = None):
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.heartbeat_s = heartbeat_s or (TTY_HEARTBEAT_S if self.tty else LOG_HEARTBEAT_S)
        self.lock = threading.Lock()
        self.t0 = time.monotonic()
        self.current = None
        self.since = time.monotonic()          # when the current update was made
        self.width = 0
        self.last_write = time.monotonic()

    def update(self, u) -> None:
        with self.lock:
            self.current, self.since = u, time.monotonic()
            self._write(self._line())

    def note(self, text: str) -> None:
        """A line of its own (e.g. one run of a batch finished); the progress line follows it."""
        with self.lock:
            self._clear()
            self.stream.write(text + "\n")
            self.last_write = time.monotonic()
            if self.current is not None and self.tty:
                self._write(self._line())
            self.stream.flush()

    def _line(self) -> str:
        u = self.current
        elapsed = time.monotonic() - self.t0
        if u is None:
            return f"working ... {duration_text(elapsed)}"
        # the estimate made when the step started, less the time since
        left = None if u.remaining is None else max(u.remaining - (time.monotonic() - self.since), 0.0)
        est = f", about {duration_text(left)} left" if left is not None and left > 0.5 else ""
        return f"[{100 * u.fraction:3.0f} %] {u.text} ({duration_text(elapsed)} elapsed{est})"

    def _write(self, line: str) -> None:
        if self.tty:
            pad = max(self.width - len(line), 0)
            self.stream.write("\r" + line + " " * pad)
            self.width = len(line)
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
        self.last_write = time.monotonic()

    def _clear(self) -> None:
        if self.tty and self.width:
            self.stream.write("\r" + " " * self.width + "\r")
            self.width = 0

    def beat(self) -> None:
        with self.lock:
            if time.monotonic() - self.last_write >= self.heartbeat_s:
                self._write(self._line())

    def finish(self, text: str | None = None) -> None:
        with self.lock:
            self._clear()
            if text:
                self.stream.write(text + "\n")
            self.stream.flush()


@dataclass(frozen=True)
class Status:
    """What a :class:`ProgressLine` shows (the fields of ``recon.progress.Update``)."""
    text: str
    fraction: float
    elapsed: float
    remaining: float | None


class Live:
    """A :class:`ProgressLine` with its heartbeat thread, from :meth:`start` to :meth:`stop`."""

    def __init__(self, stream=None):
        self.line = ProgressLine(stream)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name="progress-heartbeat", daemon=True)

    def _beat(self):
        while not self._stop.wait(min(self.line.heartbeat_s, 0.5)):
            self.line.beat()

    def start(self, text: str | None = None) -> "Live":
        if text:
            self.line.update(Status(text, 0.0, 0.0, None))
        self._thread.start()
        return self

    def stop(self, done: str | None = None) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self.line.finish(done.format(elapsed=duration_text(time.monotonic() - self.line.t0)) if done else None)


_live: Live | None = None


def start(text: str, quiet: bool = False, stream=None) -> Live | None:
    """Show ``text`` at once and keep the line alive until :func:`stop` (a command's start-up: loading
    the numerical libraries takes seconds); the job's steps take the same line over (:func:`current`)."""
    global _live
    if quiet:
        return None
    stop()
    _live = Live(stream).start(text)
    return _live


def current() -> Live | None:
    """The line a command started, if it is still showing."""
    return _live


def stop(done: str | None = None) -> None:
    global _live
    if _live is not None:
        live, _live = _live, None
        live.stop(done)
