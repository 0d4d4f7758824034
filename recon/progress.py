"""Progress of a long computation, told to whoever listens.

Library code marks its main steps and prints nothing::

    @progress.task("reconstruct")
    def reconstruct(run, settings): ...
        progress.step("fitting the two stages together", share=0.3)

The application decides how to show them::

    with progress.reporting(callback):      # callback(Update) on every step
        reconstruct(run)

A step's ``share`` is the part of its task it takes (the shares of a task's steps add up to about
1; a skipped step only makes the fraction jump). A task called inside a step of another task
(reconstruct inside diagnose) divides that step's part among its own steps, and its step names
follow the outer step's (``reconstructing the baseline: the first estimate``), so one fraction runs
from 0 to 1 over the whole job. Without a reporter every call is a no-op. The reporter is
context-local (``contextvars``): concurrent jobs in one process each report to their own.
No third-party import: recon's layer forbids presentation libraries.
"""
from __future__ import annotations

import contextvars
import functools
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable

MIN_FRACTION_FOR_ESTIMATE = 0.03     # below this share done, an estimate of the time left is noise


@dataclass(frozen=True)
class Update:
    """One step: ``text`` names it (outer tasks first, joined by ': '), ``fraction`` is the share
    of the whole job done when it started, ``elapsed`` the seconds since the job started and
    ``remaining`` an estimate of the seconds left (None while too little is done to tell)."""
    text: str
    fraction: float
    elapsed: float
    remaining: float | None


@dataclass
class _Scope:
    name: str
    start: float            # where this task begins in the whole job (0..1)
    span: float             # how much of the whole job it covers
    done: float = 0.0       # share of this task finished before its current step (0..1)
    share: float = 0.0      # share of this task its current step covers
    label: str = ""


@dataclass
class _Reporter:
    callback: Callable[[Update], None]
    t0: float = field(default_factory=time.monotonic)
    scopes: list = field(default_factory=list)

    def position(self) -> float:
        s = self.scopes[-1]
        return min(1.0, s.start + s.span * min(s.done, 1.0))

    def emit(self) -> None:
        frac = self.position()
        elapsed = time.monotonic() - self.t0
        remaining = elapsed * (1.0 - frac) / frac if frac >= MIN_FRACTION_FOR_ESTIMATE else None
        inner = self.scopes[-1]
        text = ": ".join([s.label for s in self.scopes[:-1] if s.label] + [inner.label or inner.name])
        self.callback(Update(text, frac, elapsed, remaining))


_current: contextvars.ContextVar[_Reporter | None] = contextvars.ContextVar("recon_progress", default=None)


@contextmanager
def reporting(callback: Callable[[Update], None]):
    """Report the steps of the calls inside to ``callback`` (nested ``reporting`` replaces the outer one)."""
    rep = _Reporter(callback)
    rep.scopes.append(_Scope("", 0.0, 1.0))
    token = _current.set(rep)
    try:
        yield rep
    finally:
        _current.reset(token)


def step(text: str, share: float) -> None:
    """The current task starts a step that takes ``share`` (0..1) of it."""
    rep = _current.get()
    if rep is None:
        return
    s = rep.scopes[-1]
    s.done = min(1.0, s.done + s.share)
    s.share = max(0.0, min(float(share), 1.0 - s.done))
    s.label = text
    rep.emit()


@contextmanager
def part(name: str):
    """The calls inside form a task named ``name`` within the current step."""
    rep = _current.get()
    if rep is None:
        yield
        return
    outer = rep.scopes[-1]
    start = rep.position()
    span = outer.span * outer.share if outer.share > 0 else outer.span * max(0.0, 1.0 - outer.done)
    rep.scopes.append(_Scope(name, start, span))
    try:
        yield
    finally:
        rep.scopes.pop()


def task(name: str):
    """Decorator: the function's steps form a task named ``name`` (see :func:`part`)."""

    def wrap(fn):
        @functools.wraps(fn)
        def run(*args, **kwargs):
            with part(name):
                return fn(*args, **kwargs)
        return run

    return wrap
