"""The progress of a long command on stderr (reconstruct, diagnose, report, reprocess, import).

    with progress_line(quiet=args.quiet):
        result = reconstruct(run)

Every step the library reports (:mod:`recon.progress`) is shown with its share of the whole job,
the elapsed time and an estimate of the time left. A heartbeat thread shows the current step again
while it runs, so a long step is never silent for more than a few seconds. On a terminal the line
is redrawn in place (``\\r``); otherwise (a log, a pipe) each update is one line. Nothing goes to
stdout, so ``--json`` output stays one JSON object; plain text only, no terminal escape codes.
"""
from __future__ import annotations

import sys
import threading
import time
from contextlib import contextmanager

from recon import progress
from shakerlab.words import duration_text

TTY_HEARTBEAT_S = 1.0       # a terminal line is redrawn this often
LOG_HEARTBEAT_S = 3.0       # a log gets a line this often while a step runs (the promise: never 5 s silent)


class ProgressLine:
    """Shows :class:`recon.progress.Update` objects on ``stream``; :meth:`note` adds a line of its own."""

    def __init__(self, stream=None, heartbeat_s: float | None = None):
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.heartbeat_s = heartbeat_s or (TTY_HEARTBEAT_S if self.tty else LOG_HEARTBEAT_S)
        self.lock = threading.Lock()
        self.t0 = time.monotonic()
        self.current: progress.Update | None = None
        self.since = time.monotonic()          # when the current update was made
        self.width = 0
        self.last_write = time.monotonic()

    def update(self, u: progress.Update) -> None:
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


@contextmanager
def progress_line(quiet: bool = False, stream=None, done: str | None = "done in {elapsed}"):
    """Show the progress of the calls inside on stderr (nothing when ``quiet``); yields the
    :class:`ProgressLine` (None when quiet). ``done`` is the closing line ("{elapsed}" filled in)."""
    if quiet:
        yield None
        return
    line = ProgressLine(stream)
    stop = threading.Event()

    def heartbeat():
        while not stop.wait(min(line.heartbeat_s, 0.5)):
            line.beat()

    thread = threading.Thread(target=heartbeat, name="progress-heartbeat", daemon=True)
    thread.start()
    ok = False
    try:
        with progress.reporting(line.update):
            yield line
        ok = True
    finally:
        stop.set()
        thread.join(timeout=2.0)
        line.finish(done.format(elapsed=duration_text(time.monotonic() - line.t0)) if ok and done else None)
