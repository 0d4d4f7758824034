"""The closed loop in the operator window (docs/gui.md, docs/closed-loop.md): a panel and its worker.

:class:`LoopPanel` holds the operator's choices (diagnose after the run, confirm each round, the
number of rounds) and shows the loop as it goes: the current step, the plan and its reason (refused
stages with the ceiling they cross), what was named with its fitted size and interval, and the
held-out NRMSE before and after. :class:`LoopController` runs :class:`rig.closed_loop.ClosedLoop` in
a worker thread; its notifications reach the panel as Qt signals. *Record* / *Stop* answer a plan
that waits for confirmation. *Cancel* stops the loop: a recording under way is ramped down by its
runner (the stages recorded so far are kept in the run file), a diagnosis under way ends first and
nothing more is driven.
"""
from __future__ import annotations

import threading

from PySide6 import QtCore, QtWidgets

from rig.closed_loop import DEFAULT_MAX_ROUNDS, ClosedLoop, diagnose_file, record_round


def named_text(summary: dict) -> str:
    """The named physics of a diagnosis summary (rig.closed_loop.summary): fitted size and interval."""
    lines = []
    for m in summary.get("named", []):
        ps = []
        for key, p in (m.get("parameters") or {}).items():
            iv = p.get("interval")
            ps.append(f"{key} = {p.get('value', float('nan')):.4g}"
                      + (f" [{iv[0]:.4g}, {iv[1]:.4g}]" if iv else ""))
        lines.append(f"{m['id']}: " + ", ".join(ps))
    if summary.get("ambiguous"):
        lines.append("ambiguous: " + " / ".join(summary["ambiguous"]))
    return "\n".join(lines) or (summary.get("result") or "")


def nrmse_text(summary: dict) -> str:
    b, a = summary.get("held_out_nrmse_before"), summary.get("held_out_nrmse_after")
    f = lambda v: "—" if v is None else f"{v:.4g}"  # noqa: E731
    return f"held-out NRMSE: baseline {f(b)} → with the named physics {f(a)}"


class LoopPanel(QtWidgets.QGroupBox):
    def __init__(self, parent=None):
        super().__init__("Closed loop: diagnose, run the stage that decides", parent)
        lay = QtWidgets.QGridLayout(self)
        self.enabled = QtWidgets.QCheckBox("diagnose after the run")
        self.confirm = QtWidgets.QCheckBox("confirm each added stage")
        self.confirm.setChecked(True)
        self.rounds = QtWidgets.QSpinBox()
        self.rounds.setRange(0, 10)
        self.rounds.setValue(DEFAULT_MAX_ROUNDS)
        self.rounds.setPrefix("rounds ≤ ")
        self.diagnose_button = QtWidgets.QPushButton("Diagnose last run")
        self.diagnose_button.setEnabled(False)
        self.record_button = QtWidgets.QPushButton("Record")
        self.stop_button = QtWidgets.QPushButton("Stop here")
        self.cancel_button = QtWidgets.QPushButton("Cancel")
        for b in (self.record_button, self.stop_button, self.cancel_button):
            b.setEnabled(False)
        self.step = QtWidgets.QLabel("idle")
        self.plan = QtWidgets.QPlainTextEdit()
        self.plan.setReadOnly(True)
        self.plan.setMaximumHeight(90)
        self.named = QtWidgets.QLabel("")
        self.named.setWordWrap(True)
        self.nrmse = QtWidgets.QLabel("")
        lay.addWidget(self.enabled, 0, 0)
        lay.addWidget(self.confirm, 0, 1)
        lay.addWidget(self.rounds, 0, 2)
        lay.addWidget(self.diagnose_button, 0, 3)
        lay.addWidget(self.step, 1, 0, 1, 4)
        lay.addWidget(self.plan, 2, 0, 1, 4)
        lay.addWidget(self.named, 3, 0, 1, 4)
        lay.addWidget(self.nrmse, 4, 0, 1, 4)
        lay.addWidget(self.record_button, 5, 1)
        lay.addWidget(self.stop_button, 5, 2)
        lay.addWidget(self.cancel_button, 5, 3)

    def busy(self, on: bool) -> None:
        self.cancel_button.setEnabled(on)
        self.diagnose_button.setEnabled(not on)
        self.enabled.setEnabled(not on)
        self.rounds.setEnabled(not on)
        if not on:
            self.awaiting(False)

    def awaiting(self, on: bool) -> None:
        self.record_button.setEnabled(on)
        self.stop_button.setEnabled(on)


class _Signals(QtCore.QObject):
    step = QtCore.Signal(str)
    plan = QtCore.Signal(object)            # RoundPlan
    ask = QtCore.Signal(object)             # RoundPlan waiting for Record / Stop
    diagnosis = QtCore.Signal(object)       # {"round", "summary", "diagnosis"}
    done = QtCore.Signal(object)            # LoopResult
    failed = QtCore.Signal(str)


class LoopController(QtCore.QObject):
    """Runs the loop on one run file for a panel. ``config``/``protocol``: the rig config (with the
    addresses the run used) and the protocol of the run; ``observers``: the window's live display and
    bridge; ``on_runner``: the window's hook (ABORT reaches the added stages' runner too);
    ``diagnose``: tests give a scripted one."""

    finished = QtCore.Signal(object)        # LoopResult (or None after a failure)

    def __init__(self, panel: LoopPanel, path, config, protocol, *, lockstep: bool = False, observers=(),
                 on_runner=None, diagnose=None, parent=None):
        super().__init__(parent)
        self.panel = panel
        self.path = path
        self.s = _Signals()
        self.result = None
        self.error = ""
        self._runner = None
        self._answer = threading.Event()
        self._accepted = False
        self._thread: threading.Thread | None = None

        def hook(runner):
            self._runner = runner
            if on_runner is not None:
                on_runner(runner)
            if self.loop.cancelled.is_set():
                runner.abort("closed loop cancelled")

        def record(plan):
            return record_round(config, protocol, path, plan, lockstep=lockstep, observers=list(observers),
                                on_runner=hook)

        confirm = self._confirm if panel.confirm.isChecked() else None
        self.loop = ClosedLoop(path, config.limits, diagnose=diagnose or diagnose_file, record=record,
                               confirm=confirm, observer=self._observe, max_rounds=panel.rounds.value())
        s = self.s
        s.step.connect(panel.step.setText)
        s.plan.connect(lambda plan: panel.plan.setPlainText(plan.text()))
        s.ask.connect(self._ask)
        s.diagnosis.connect(self._show_diagnosis)
        s.done.connect(self._done)
        s.failed.connect(self._failed)
        panel.record_button.clicked.connect(lambda: self.answer(True))
        panel.stop_button.clicked.connect(lambda: self.answer(False))
        panel.cancel_button.clicked.connect(self.cancel)

    # -- worker thread ---------------------------------------------------------------------------
    def start(self) -> None:
        self.panel.busy(True)
        self.panel.plan.clear()
        self.panel.named.setText("")
        self.panel.nrmse.setText("")

        def work():
            try:
                self.s.done.emit(self.loop.run())
            except Exception as exc:  # noqa: BLE001 - shown to the operator; the run file stays as recorded
                self.s.failed.emit(f"{type(exc).__name__}: {exc}")

        self._thread = threading.Thread(target=work, name="gui-closed-loop", daemon=True)
        self._thread.start()

    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    def _observe(self, event: str, payload) -> None:
        if event == "diagnosing":
            self.s.step.emit(f"round {payload['round']}: diagnosing "
                             f"{'the run' if payload['round'] == 0 else 'the extended run'} …")
        elif event == "diagnosis":
            self.s.diagnosis.emit(payload)
        elif event == "plan":
            self.s.plan.emit(payload)
        elif event == "recording":
            self.s.step.emit(f"round {payload.round}: recording "
                             + ", ".join(st.name for st in payload.accepted) + " …")
        elif event == "recorded":
            self._runner = None

    def _confirm(self, plan) -> bool:
        self._answer.clear()
        self.s.ask.emit(plan)
        while not self._answer.wait(0.1):
            if self.loop.cancelled.is_set():
                return False
        return self._accepted

    # -- GUI thread -------------------------------------------------------------------------------
    def _ask(self, plan) -> None:
        self.panel.step.setText(f"round {plan.round}: record the planned stage(s)?")
        self.panel.awaiting(True)

    def answer(self, accepted: bool) -> None:
        self._accepted = accepted
        self.panel.awaiting(False)
        self._answer.set()

    def cancel(self) -> None:
        """Stop the loop: a recording under way ramps down (what it recorded is kept)."""
        self.loop.cancel()
        runner = self._runner
        if runner is not None:
            runner.abort("closed loop cancelled")
        self._answer.set()
        self.panel.step.setText("cancelling …")

    def _show_diagnosis(self, payload) -> None:
        sm = payload["summary"]
        self.panel.step.setText(f"round {payload['round']}: {sm.get('result')}")
        self.panel.named.setText(named_text(sm))
        self.panel.nrmse.setText(nrmse_text(sm))

    def _done(self, result) -> None:
        self.result = result
        self.panel.busy(False)
        self.panel.step.setText(f"stopped ({result.stop}): {result.stop_reason}")
        if not result.rounds:
            self.panel.plan.setPlainText("no stage added: the first diagnosis decided")
        self.finished.emit(result)

    def _failed(self, message: str) -> None:
        self.error = message
        self.panel.busy(False)
        self.panel.step.setText(f"failed: {message}")
        self.finished.emit(None)
