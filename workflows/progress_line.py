"""A job's steps (:mod:`recon.progress`) on stderr, through :mod:`shakerlab.progress_view`.

    with progress_line(quiet=args.quiet):
        result = reconstruct(run)

The line a command started while it loaded (``shakerlab.progress_view.start``) is taken over, so
the output never pauses between start-up and the first step; otherwise a new one is made.
"""
from __future__ import annotations

from contextlib import contextmanager

from recon import progress
from shakerlab import progress_view


@contextmanager
def progress_line(quiet: bool = False, stream=None, done: str | None = "done in {elapsed}"):
    """Show the progress of the calls inside on stderr (nothing when ``quiet``); yields the
    :class:`shakerlab.progress_view.ProgressLine` (None when quiet). ``done`` is the closing line
    ("{elapsed}" filled in)."""
    if quiet:
        progress_view.stop()
        yield None
        return
    live = progress_view.current() or progress_view.Live(stream).start()
    ok = False
    try:
        with progress.reporting(live.line.update):
            yield live.line
        ok = True
    finally:
        if live is progress_view.current():
            progress_view.stop(done if ok else None)
        else:
            live.stop(done if ok else None)
