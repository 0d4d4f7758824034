"""Diagnose a recorded run from the operator window (no Qt here): :func:`recon.diagnose` in a child
process, its progress, a cancel, and what the diagnosis view shows.

:class:`DiagnosisJob` runs in the window's ``gui-diagnose`` worker thread. It starts a child process
(``spawn``: nothing of the window's threads is copied) that loads the run file, runs
``recon.diagnose`` and sends back progress messages and, at the end, a :class:`DiagnosisView`. A
child process is what makes *Cancel* real: the diagnosis has no cancellation point of its own, and
terminating the child stops it at once without leaving a half-finished computation in the window's
process. Progress comes from the diagnosis's own steps (the baseline, the reference fits, the
located mismatch, one fit per catalog candidate, the detection limits and the pair search), seen as
the child calls them; a step the diagnosis no longer has is simply not reported.

The result is written back into the run file as ``entry/results/diagnosis_NNN`` (when the file was
closed cleanly), so the Results tab shows it the next time the file is opened.
"""
from __future__ import annotations

import multiprocessing as mp
import queue
import sys
import time
import traceback
from dataclasses import dataclass, field

import numpy as np

from rig.gui.results import fn_unit
from shakerlab.words import nrmse_text

# the diagnosis's steps as the child sees them called: (file, function, share of the run where the
# step starts, message). One fit per catalog candidate fills CANDIDATES_SPAN (their count is known).
STEPS = (("diagnose.py", "resolve_baseline", 0.00, "reconstructing the baseline model"),
         ("references.py", "reference_fits", 0.25, "refitting the baseline (null model)"),
         ("locate.py", "locate", 0.35, "locating the mismatch"),
         ("candidate_fit.py", "fit_candidate", 0.40, "fitting candidate"),
         ("sensitivity.py", "detection_limits", 0.90, "estimating detection limits"),
         ("refits.py", "joint_pair", 0.93, "trying pairs of candidates"))
CANDIDATES_SPAN = (0.40, 0.90)
POLL_S = 0.1


@dataclass
class Progress:
    step: str            # what the diagnosis is doing now
    fraction: float      # 0..1 of the whole (from the steps' shares: an estimate)
    elapsed_s: float

    def eta_s(self) -> float | None:
        """Seconds left, extrapolated from the time so far (None until 5 % is done)."""
        if self.fraction < 0.05:
            return None
        return self.elapsed_s * (1.0 - self.fraction) / self.fraction

    def text(self) -> str:
        eta = self.eta_s()
        return (f"{self.step} ({self.fraction * 100:.0f} %, {self.elapsed_s:.0f} s"
                + (f", about {eta:.0f} s left)" if eta is not None else ")"))


@dataclass
class DiagnosisView:
    source: str
    baseline_kind: str
    result: str                       # the diagnosis's one-line result
    named: list                       # rows: (id, explanation, [(parameter, value, unit)], held-out before, after)
    stages: list                      # rows: (stage, NRMSE before, after)
    held_before: float                # held-out NRMSE of the reference (baseline as given or refitted)
    held_after: float                 # held-out NRMSE of the augmented model
    overlay: tuple | None             # (stage, t, recorded, baseline, augmented) on the held-out samples [s, m]
    unexplained: str | None = None    # the mismatch the final model still leaves, if large
    baseline_note: str | None = None
    detection_limits: list = field(default_factory=list)   # (id, parameter, value) when nothing is named
    equation: str = ""                # the augmented model
    origin: str = ""
    seconds: float = 0.0
    payload: dict = field(default_factory=dict, repr=False)   # diagnosis.to_dict(), JSON-ready

    def level(self) -> str:
        """green: named and nothing large left, or nothing to name; amber: named, but a mismatch
        above the noise is left (partly explained); red: a mismatch above the noise, nothing named."""
        if self.unexplained:
            return "amber" if self.named else "red"
        return "green"

    def sentence(self) -> str:
        before, after = nrmse_text(self.held_before), nrmse_text(self.held_after)
        if self.named:
            names = ", ".join(f"{cid} ({_sizes(params)})" for cid, _, params, _, _ in self.named)
            out = f"Found: {names}; held-out NRMSE {before} → {after}."
            if self.unexplained:
                out += " Partly explained: a mismatch above the noise is left."
            return out
        if self.unexplained:
            return f"Unexplained: a mismatch above the noise (held-out NRMSE {before}) that no catalog effect explains."
        return f"Nothing missing: no catalog effect explains the held-out mismatch beyond the noise (NRMSE {before})."


def _sizes(params: list) -> str:
    return ", ".join(f"{name} = {value:.4g}{(' ' + unit) if unit else ''}" for name, value, unit in params)


def view_of_diagnosis(d, run, source: str) -> DiagnosisView:
    """The view of a :class:`recon.Diagnosis` of ``run``."""
    from recon.diagnosis import rank  # heavy: recon, loaded in the diagnosis child process
    from shakerlab.jsonsafe import clean  # heavy: recon, loaded in the diagnosis child process

    out = clean(d.to_dict())
    named = []
    for m in out["missing_physics"]:
        params = [(k, float(v["value"]), unit_of(k)) for k, v in m["parameters"].items()
                  if isinstance(v, dict) and v.get("value") is not None]
        ev = m.get("evidence", {})
        named.append((m["id"], m.get("explanation", ""), params, ev.get("held_out_nrmse_before"),
                      ev.get("held_out_nrmse_after")))
    fb, fa = out["fit_before"]["nrmse"], out["fit_after"]["nrmse"]
    stages = [(s, fb[s], fa.get(s)) for s in fb]
    reference = d.reference if d.reference is not None else d.null
    overlay = None
    data = rank.prepare(run, d.baseline.baseline)
    for i, sd in enumerate(data):
        if sd.held.any() and reference.sims is not None and d.best_fit.sims is not None:
            h = sd.held
            overlay = (sd.name, sd.t[h] - sd.t[h][0], sd.y[h], reference.sims[i][h], d.best_fit.sims[i][h])
            break
    limits = [(c["id"], c["detection_limit"]["parameter"], float(c["detection_limit"]["value"]))
              for c in out["candidates_tested"] if (c.get("detection_limit") or {}).get("value") is not None]
    um = out.get("unexplained_mismatch")
    return DiagnosisView(source=source, baseline_kind=out["baseline_kind"], result=out["result"], named=named,
                         stages=stages, held_before=reference.nrmse_held, held_after=d.best_fit.nrmse_held,
                         overlay=overlay, unexplained=(um.get("note") if isinstance(um, dict) else None),
                         baseline_note=out.get("baseline_note"), detection_limits=limits,
                         equation=out["fit_after"]["model"], seconds=float(out.get("seconds", 0.0)), payload=out)


class _StepWatch:
    """A trace function that reports the diagnosis's steps (:data:`STEPS`) as they are called.

    Only function calls are seen (it returns None: no line events), so it costs one cheap Python
    call per Python function call of the child. The share reported never goes back."""

    def __init__(self, send, n_candidates: int):
        self.send = send
        self.n = max(1, n_candidates)
        self.seen: list = []
        self.share = 0.0
        self.t0 = time.perf_counter()
        self.steps = {name: (file, share, text) for file, name, share, text in STEPS}

    def __call__(self, frame, event, arg):
        step = self.steps.get(frame.f_code.co_name) if event == "call" else None
        if step is None or not frame.f_code.co_filename.endswith(step[0]):
            return None
        _, share, text = step
        if frame.f_code.co_name == "fit_candidate":
            cid = frame.f_locals.get("cid")
            if cid not in self.seen:
                self.seen.append(cid)
            i = self.seen.index(cid) + 1
            lo, hi = CANDIDATES_SPAN
            share = lo + (hi - lo) * (i - 1) / self.n
            text = f"fitting candidate {cid} ({i} of {self.n})"
        self.share = max(self.share, min(share, 0.99))
        self.send(("progress", text, self.share, time.perf_counter() - self.t0))
        return None


def unit_of(name: str) -> str:
    """The unit of a parameter a diagnosis reports: a catalog extra, a baseline parameter or an fn term."""
    from recon.diagnosis.augmented import EXTRAS  # heavy: recon, loaded in the diagnosis child process
    from recon.model import UNITS  # heavy: recon, loaded in the diagnosis child process

    if name in EXTRAS:
        return "" if EXTRAS[name][1] == "-" else EXTRAS[name][1]
    if name in UNITS and name != "fn_m":
        return UNITS[name]
    return fn_unit(name.removeprefix("fn_m[").removesuffix("]"))


def _child(path: str, baseline, candidates, out) -> None:
    """The child process: load, diagnose with the steps watched, send the view (or the error)."""
    try:
        from recon import diagnose  # heavy: recon, loaded in the diagnosis child process
        from recon.diagnosis.catalog import CATALOG  # heavy: recon, loaded in the diagnosis child process
        from shakerlab.runfile.reader import load_run  # heavy: loaded in the diagnosis child process

        out.put(("progress", "reading the run file", 0.0, 0.0))
        run = load_run(path)
        watch = _StepWatch(out.put, len(candidates or CATALOG))
        sys.settrace(watch)
        try:
            d = diagnose(run, baseline=baseline, candidates=candidates)
        finally:
            sys.settrace(None)
        out.put(("progress", "simulating the held-out overlay", 0.99, time.perf_counter() - watch.t0))
        out.put(("done", view_of_diagnosis(d, run, path)))
    except Exception as exc:  # noqa: BLE001 - sent to the window, shown to the operator
        from shakerlab.errors import UserFacingError  # lazy: only on an error

        msg = str(exc) if isinstance(exc, UserFacingError) else f"{type(exc).__name__}: {exc}"
        out.put(("error", msg, traceback.format_exc()))


class Cancelled(Exception):
    """The operator cancelled the diagnosis."""


class DiagnosisJob:
    """``recon.diagnose`` of a run file in a child process; :meth:`run` blocks (call it from a worker
    thread), :meth:`cancel` may be called from any thread."""

    def __init__(self, path, baseline="paper", candidates=None, on_progress=None, write_back: bool = True):
        self.path = str(path)
        self.baseline = baseline
        self.candidates = list(candidates) if candidates else None
        self.on_progress = on_progress or (lambda p: None)
        self.write_back = write_back
        self.process = None
        self._cancelled = False

    def cancel(self) -> None:
        self._cancelled = True
        p = self.process
        if p is not None and p.is_alive():
            p.terminate()

    @property
    def cancelled(self) -> bool:
        return self._cancelled

    def run(self) -> DiagnosisView:
        """The view of the diagnosis; raises :class:`Cancelled`, or UserFacingError with the child's message."""
        from shakerlab.errors import UserFacingError  # lazy: keeps this module free of imports at window start-up

        ctx = mp.get_context("spawn")
        out = ctx.Queue()
        t0 = time.perf_counter()
        self.process = ctx.Process(target=_child, args=(self.path, self.baseline, self.candidates, out),
                                   name="shakerlab-diagnose", daemon=True)
        if self._cancelled:
            raise Cancelled()
        self.process.start()
        last = Progress("starting the diagnosis", 0.0, 0.0)
        try:
            while True:
                if self._cancelled:
                    raise Cancelled()
                try:
                    msg = out.get(timeout=POLL_S)
                except queue.Empty:
                    if not self.process.is_alive():
                        if self._cancelled:
                            raise Cancelled() from None
                        try:   # the last message may arrive after the process ended
                            msg = out.get(timeout=1.0)
                        except queue.Empty:
                            raise UserFacingError(f"the diagnosis process ended without a result "
                                                  f"(exit code {self.process.exitcode})") from None
                    else:
                        last = Progress(last.step, last.fraction, time.perf_counter() - t0)
                        self.on_progress(last)
                        continue
                if msg[0] == "progress":
                    last = Progress(msg[1], float(msg[2]), time.perf_counter() - t0)
                    self.on_progress(last)
                elif msg[0] == "error":
                    raise UserFacingError(f"diagnosis of {self.path}: {msg[1]}")
                else:
                    view = msg[1]
                    break
        finally:
            if self.process.is_alive():
                self.process.terminate()
            self.process.join(5)
            out.close()
        view.origin = "diagnosed now" + (self._store(view) if self.write_back else "")
        self.on_progress(Progress("done", 1.0, time.perf_counter() - t0))
        return view

    def _store(self, view: DiagnosisView) -> str:
        from shakerlab.runfile.results import store_result  # heavy: loaded when a diagnosis is stored

        text = view.sentence() + "\n" + view.result + ("\naugmented model:\n" + view.equation if view.named else "")
        group, note = store_result(self.path, "diagnosis", dict(view.payload, text=text), text=text)
        return f", written to entry/results/{group}" if group else f" ({note})"


def overlay_arrays(view: DiagnosisView):
    """(t, recorded, baseline, augmented) of the overlay, or four empty arrays."""
    if view.overlay is None:
        return (np.array([]),) * 4
    return tuple(np.asarray(a, float) for a in view.overlay[1:])

