"""The operator's main window: drives :func:`rig.session.acquire` (the same runner as the
headless ``shakerlab acquire``) from a worker thread and shows the run live and its result.

Threads:

- the GUI thread owns every widget; a QTimer (``FPS`` per second) redraws the
  live plots from :class:`rig.gui.live_state.LiveData` (ring buffers);
- the run worker (a ``threading.Thread``) starts the simulated rig when the
  switch is on, and runs ``acquire``; runner notifications reach the GUI as
  Qt signals (queued across threads), samples go to the ring buffers only;
- the reconstruction worker reads the run file and reconstructs the model
  (:func:`rig.gui.results.view_of_run_file`), then hands the view back by signal.

ABORT calls ``Runner.abort``: the first press ramps the output to zero in the
rig's ``abort_ramp_s`` and stops, a second press cuts at once. Closing the
window mid-run aborts the same way and closes the window once the run has
ended (output off, amplifier muted, run file closed).
"""
from __future__ import annotations

import datetime as _dt
import threading
import time
import tomllib
from pathlib import Path

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets

from rig.gui.live_state import LiveData
from rig.gui.diagnosis import Cancelled, DiagnosisJob
from rig.gui.loop_panel import LoopController, LoopPanel
from rig.gui.panels import (LOOP_TITLE, ConnectionPanel, DiagnosisPanel, LivePlots, ProtocolPanel, ResultsPanel,
                            set_series)
from shakerlab.errors import UserFacingError

FPS = 25
TRACE_SECONDS = 5.0
LAG_THROTTLE_S = 0.3   # acquisition this far behind real time: redraw at FPS / THROTTLE (acquisition first)
LAG_RESUME_S = 0.1
THROTTLE = 5
LEVEL_COLORS = {"debug": "#888888", "info": "#202020", "warning": "#b06000", "error": "#c00000",
                "critical": "#c00000"}


class _Signals(QtCore.QObject):
    """Everything the worker threads tell the GUI thread."""

    run_started = QtCore.Signal(object)          # info dict
    state = QtCore.Signal(str)
    stage_begun = QtCore.Signal(str, object, int)
    stage_ended = QtCore.Signal(str, str, object)
    event = QtCore.Signal(str, str, float)
    finished = QtCore.Signal(object)             # RunOutcome
    failed = QtCore.Signal(str)
    connected = QtCore.Signal(object, object)    # identities, addresses
    connect_failed = QtCore.Signal(str)
    result_ready = QtCore.Signal(object)         # ResultView
    result_failed = QtCore.Signal(str)
    diagnosis_progress = QtCore.Signal(object)   # rig.gui.diagnosis.Progress
    diagnosis_ready = QtCore.Signal(object)      # DiagnosisView
    diagnosis_failed = QtCore.Signal(str)
    diagnosis_cancelled = QtCore.Signal()


class _Bridge:
    """Runner observer that forwards the discrete notifications as Qt signals (blocks stay out)."""

    def __init__(self, signals: _Signals):
        self.s = signals

    def on_run_start(self, info):
        self.s.run_started.emit(dict(info))

    def on_state(self, state):
        self.s.state.emit(state)

    def on_stage_begin(self, name, settings, index):
        self.s.stage_begun.emit(name, dict(settings), int(index))

    def on_stage_end(self, name, status, summary):
        self.s.stage_ended.emit(name, status, dict(summary))

    def on_event(self, level, message, run_time):
        self.s.event.emit(level, message, float(run_time))


class MainWindow(QtWidgets.QMainWindow):
    def __init__(self, *, config_path: str | Path | None = None, protocol_path: str | Path | None = None,
                 output_dir: str | Path = "shakerlab-runs", simulated: bool | None = None, speed: float = 1.0,
                 seed: int = 0, auto_reconstruct: bool = True):
        super().__init__()
        self.setWindowTitle("shakerlab — operator")
        self.output_dir = Path(output_dir)
        self.seed = seed
        self.auto_reconstruct = auto_reconstruct
        self.signals = _Signals()
        self.live = LiveData()
        self.sim = None                    # SimulatedRig while the switch is on and it was started
        self._sim_speed = None
        self._sim_lock = threading.Lock()
        self._runner = None
        self._run_thread: threading.Thread | None = None
        self._recon_thread: threading.Thread | None = None
        self._diag_thread: threading.Thread | None = None
        self._diag_job: DiagnosisJob | None = None
        self.last_diagnosis = None          # DiagnosisView of the last diagnosis finished here
        self.diagnosis_state = "idle"       # idle, running, done, cancelled, failed
        self._abort_presses = 0
        self._close_pending = False
        self._stage_t0 = None
        self._n_stages = 1
        self.run_path: Path | None = None
        self._run_simulated = False
        self.last_outcome = None
        self.last_view = None
        self.last_error = ""
        self.frames = 0                    # live redraws done (for bench/gui_fps.py)
        self.ticks = 0                     # redraw timer ticks
        self.throttled = False             # redrawing slower because the acquisition fell behind
        self.throttled_ticks = 0
        self._run_speed = 0.0              # real time factor of the running rig (0: lockstep)
        self.redraw_seconds = 0.0          # time spent in them
        self.redraw_times: list[float] = []  # the last 1000 redraw durations [s]
        self._build(config_path, protocol_path, simulated, speed)
        self._wire()
        self.timer = QtCore.QTimer(self)
        self.timer.setInterval(int(1000 / FPS))
        self.timer.timeout.connect(self._redraw)
        self.timer.start()

    # -- layout -----------------------------------------------------------------------------------
    def _build(self, config_path, protocol_path, simulated, speed) -> None:
        self.tabs = QtWidgets.QTabWidget()
        self.setCentralWidget(self.tabs)
        run_tab = QtWidgets.QSplitter(QtCore.Qt.Horizontal)
        left = QtWidgets.QWidget()
        ll = QtWidgets.QVBoxLayout(left)
        ll.setContentsMargins(4, 4, 4, 4)
        self.connection = ConnectionPanel()
        self.protocol_panel = ProtocolPanel()
        ll.addWidget(self.connection)
        ll.addWidget(self.protocol_panel, 1)
        self.loop_panel = LoopPanel()       # the closed loop (rig/gui/loop_panel.py)
        ll.addWidget(self.loop_panel)
        self.loop = None                    # LoopController while a loop runs or after it
        self._loop_args = None              # (config with addresses, protocol, lockstep) of the last run
        self.loop_diagnose = None           # the loop's diagnosis of a run file (None: recon.diagnose)
        self.log_view = QtWidgets.QPlainTextEdit()
        self.log_view.setReadOnly(True)
        self.log_view.setMaximumBlockCount(2000)
        self.log_view.setMaximumHeight(150)
        ll.addWidget(self.log_view)
        run_tab.addWidget(left)
        self.plots = LivePlots()
        run_tab.addWidget(self.plots)
        run_tab.setSizes([470, 930])
        self.tabs.addTab(run_tab, "Run")
        self.results = ResultsPanel()
        self.tabs.addTab(self.results, "Results")
        self.diagnosis = DiagnosisPanel()
        self.tabs.addTab(self.diagnosis, "Diagnosis")
        self.statusBar().showMessage("ready")
        menu = self.menuBar().addMenu("&File")
        self.open_action = menu.addAction("&Open run file…")
        self.open_action.setShortcut(QtGui.QKeySequence.Open)
        menu.addAction("&Quit", self.close)

        if config_path:
            self.connection.config_path.setText(str(config_path))
        self.connection.simulated.setChecked(config_path is None if simulated is None else simulated)
        self.connection.speed.setValue(speed)
        self.load_protocol_file(protocol_path)
        try:
            self._show_config(self.config())
        except UserFacingError as exc:
            self.log("error", str(exc))

    def _wire(self) -> None:
        s = self.signals
        s.run_started.connect(self._on_run_started)
        s.state.connect(self._on_state)
        s.stage_begun.connect(self._on_stage_begun)
        s.stage_ended.connect(self._on_stage_ended)
        s.event.connect(lambda level, msg, t: self.log(level, msg, t))
        s.finished.connect(self._on_finished)
        s.failed.connect(self._on_failed)
        s.connected.connect(self._on_connected)
        s.connect_failed.connect(self._on_connect_failed)
        s.result_ready.connect(self._on_result)
        s.result_failed.connect(self._on_result_failed)
        s.diagnosis_progress.connect(self.diagnosis.show_progress)
        s.diagnosis_ready.connect(self._on_diagnosis)
        s.diagnosis_failed.connect(self._on_diagnosis_failed)
        s.diagnosis_cancelled.connect(self._on_diagnosis_cancelled)
        p = self.protocol_panel
        p.start_button.clicked.connect(self.start_run)
        p.pause_button.toggled.connect(self._pause_toggled)
        p.abort_button.clicked.connect(self.abort)
        p.load_button.clicked.connect(self._choose_protocol)
        p.save_button.clicked.connect(self._save_protocol)
        c = self.connection
        c.connect_button.clicked.connect(self.connect_instruments)
        c.browse.clicked.connect(self._choose_config)
        c.config_path.editingFinished.connect(self._config_edited)
        c.simulated.toggled.connect(self._simulated_toggled)
        self.results.open_button.clicked.connect(self._choose_run)
        self.results.reconstruct_button.clicked.connect(lambda: self.open_run(self.results_path, reconstruct=True))
        self.results.law_button.clicked.connect(self._choose_law)
        self.results.diagnose_button.clicked.connect(lambda: self.diagnose_run())
        self.diagnosis.start_button.clicked.connect(lambda: self.diagnose_run())
        self.diagnosis.cancel_button.clicked.connect(self.cancel_diagnosis)
        self.open_action.triggered.connect(self._choose_run)
        self.results_path = None
        self.loop_panel.diagnose_button.clicked.connect(self.start_loop)

    # -- helpers --------------------------------------------------------------------------------
    def log(self, level: str, message: str, run_time: float | None = None) -> None:
        stamp = _dt.datetime.now().strftime("%H:%M:%S")
        rt = f" [{run_time:7.2f} s]" if run_time is not None and np.isfinite(run_time) else ""
        color = LEVEL_COLORS.get(level, "#202020")
        text = message.replace("&", "&amp;").replace("<", "&lt;")
        self.log_view.appendHtml(f'<span style="color:{color}">{stamp}{rt} {level}: {text}</span>')
        if level in ("warning", "error", "critical"):
            self.statusBar().showMessage(message, 10000)

    def running(self) -> bool:
        return self._run_thread is not None and self._run_thread.is_alive()

    def loop_running(self) -> bool:
        return self.loop is not None and self.loop.running()

    def config(self):
        from rig.config import load_config  # lazy: loaded when the operator uses it (window start-up time)

        text = self.connection.config_path.text().strip()
        return load_config(text or None)

    def protocol(self):
        """The protocol in the editor (validated); the source names the file it came from."""
        from rig.protocol import parse_protocol  # lazy: loaded when the operator uses it (window start-up time)

        text = self.protocol_panel.editor.toPlainText()
        source = self._protocol_source + (" (edited)" if text != self._protocol_text else "")
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise UserFacingError(f"{source}: not valid TOML: {exc}") from None
        return parse_protocol(data, text, source)

    def load_protocol_file(self, path) -> None:
        from rig.protocol import DEFAULT_PROTOCOL_PATH  # lazy: loaded when the operator uses it (window start-up time)

        p = Path(path) if path else DEFAULT_PROTOCOL_PATH
        try:
            text = p.read_text(encoding="utf-8")
        except OSError as exc:
            raise UserFacingError(f"protocol file {p}: cannot read it ({exc})") from None
        self._protocol_source, self._protocol_text = str(p), text
        self.protocol_panel.editor.setPlainText(text)
        self.protocol_panel.source.setText(str(p))
        self._show_control_plot()

    def set_protocol_text(self, text: str, source: str = "protocol (typed in)") -> None:
        self._protocol_source, self._protocol_text = source, text
        self.protocol_panel.editor.setPlainText(text)
        self.protocol_panel.source.setText(source)
        self._show_control_plot()

    def _show_control_plot(self, protocol=None) -> None:
        """The sine-control plot is shown only for a closed-loop protocol (one giving base targets)."""
        from rig.control_plans import base_targets  # lazy: loaded when the operator uses it (window start-up time)

        if protocol is None:
            try:
                protocol = self.protocol()
            except UserFacingError:
                return             # an editor that does not parse yet: the plot stays as it is
        self.plots.set_control_visible(bool(base_targets(protocol)))

    def _show_config(self, config) -> None:
        self.protocol_panel.show_limits(config.limits)
        if self.connection.simulated.isChecked():
            self.connection.show_addresses(self.sim.addresses if self.sim else
                                           {k: "(simulated rig, started with the run)" for k in
                                            ("generator", "amplifier", "sensor_base", "sensor_tip")})
        else:
            self.connection.show_addresses(config.addresses())

    def _config_edited(self) -> None:
        try:
            self._show_config(self.config())
        except UserFacingError as exc:
            self.log("error", str(exc))

    def _error_box(self, message: str) -> None:
        self.last_error = message
        self.log("error", message)
        if QtWidgets.QApplication.platformName() != "offscreen":
            QtWidgets.QMessageBox.critical(self, "shakerlab", message)

    # -- file dialogs -----------------------------------------------------------------------------
    def _choose_protocol(self) -> None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Load protocol", "", "TOML (*.toml);;all (*)")
        if path:
            try:
                self.load_protocol_file(path)
            except UserFacingError as exc:
                self._error_box(str(exc))

    def _save_protocol(self) -> None:
        path, _ = QtWidgets.QFileDialog.getSaveFileName(self, "Save protocol", "", "TOML (*.toml)")
        if path:
            text = self.protocol_panel.editor.toPlainText()
            Path(path).write_text(text, encoding="utf-8")
            self._protocol_source, self._protocol_text = path, text
            self.protocol_panel.source.setText(path)

    def _choose_config(self) -> None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Rig config", "", "TOML (*.toml);;all (*)")
        if path:
            self.connection.config_path.setText(path)
            self._config_edited()

    def _choose_run(self) -> None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Open run file", str(self.output_dir),
                                                        "run files (*.h5 *.hdf5 *.nxs *.npz);;all (*)")
        if path:
            self.open_run(path)

    # -- simulated rig ------------------------------------------------------------------------------
    def _ensure_sim(self):
        """Start (or restart at another speed) the simulated rig; worker threads only."""
        from sim_backend.rig import SimulatedRig  # lazy: loaded when the operator uses it (window start-up time)

        v = self.connection.speed.value()
        speed = None if v == 0 else float(v)
        with self._sim_lock:
            if self.sim is not None and self._sim_speed != speed:
                self.sim.stop()
                self.sim = None
            if self.sim is None:
                sim = SimulatedRig(None, speed=speed, seed=self.seed)
                sim.start()
                self.sim, self._sim_speed = sim, speed
            return self.sim

    def stop_sim(self) -> None:
        with self._sim_lock:
            if self.sim is not None and not self.running():
                self.sim.stop()
                self.sim = None

    def _simulated_toggled(self, on: bool) -> None:
        if not on:
            self.stop_sim()
        self.connection.light_connected.set("off", "")
        self.connection.show_identities({})
        self._config_edited()

    # -- connect ----------------------------------------------------------------------------------
    def connect_instruments(self) -> None:
        """Open every instrument, read its identity, close again (worker thread)."""
        if self.running():
            return
        try:
            config = self.config()
        except UserFacingError as exc:
            self._error_box(str(exc))
            return
        simulated = self.connection.simulated.isChecked()
        self.connection.connect_button.setEnabled(False)

        def work():
            from rig.instruments import RigInstruments  # lazy: loaded when the operator uses it (window start-up time)

            try:
                cfg = config.with_addresses(self._ensure_sim().addresses) if simulated else config
                inst = RigInstruments(cfg)
                try:
                    ids = inst.connect()
                finally:
                    inst.close()
                self.signals.connected.emit(ids, cfg.addresses())
            except Exception as exc:  # noqa: BLE001 - shown to the operator
                self.signals.connect_failed.emit(f"{type(exc).__name__}: {exc}" if not isinstance(exc, UserFacingError)
                                                 else str(exc))

        threading.Thread(target=work, name="gui-connect", daemon=True).start()

    def _on_connected(self, identities, addresses) -> None:
        self.connection.connect_button.setEnabled(True)
        self.connection.show_addresses(addresses)
        self.connection.show_identities(identities)
        self.connection.light_connected.set("ok", "every instrument answered its identification query")
        self.log("info", "connected: " + "; ".join(f"{k} = {v}" for k, v in identities.items()))

    def _on_connect_failed(self, message: str) -> None:
        self.connection.connect_button.setEnabled(True)
        self.connection.light_connected.set("bad", message)
        self._error_box(f"connection failed: {message}")

    # -- run control -------------------------------------------------------------------------------
    def new_run_path(self) -> Path:
        stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        path = self.output_dir / f"run-{stamp}.h5"
        i = 1
        while path.exists():
            path = self.output_dir / f"run-{stamp}-{i}.h5"
            i += 1
        return path

    def start_run(self) -> bool:
        """Validate the config and the protocol, then run them in the worker thread."""
        if self.running() or self.loop_running():
            return False
        try:
            config = self.config()
            protocol = self.protocol()
            protocol.check_against_limits(config.limits, config.source)
            self.output_dir.mkdir(parents=True, exist_ok=True)
        except UserFacingError as exc:
            self._error_box(str(exc))
            return False
        except OSError as exc:
            self._error_box(f"output directory {self.output_dir}: {exc}")
            return False
        simulated = self.connection.simulated.isChecked()
        self._run_simulated = simulated
        speed = self.connection.speed.value()
        self._run_speed = (float(speed) if speed > 0 else 0.0) if simulated else 1.0
        self.throttled = False
        path = self.new_run_path()
        self.run_path = path
        self.last_outcome = None
        self.last_error = ""
        self._runner = None
        self._abort_presses = 0
        self.live.reset()
        self.plots.reset()
        self.protocol_panel.linear_label.setText("linear step: not yet known")
        self._show_config(config)
        self._show_control_plot(protocol)
        self._n_stages = 2 + int(protocol["resonance_search"]["enabled"]) + len(protocol.validation)
        p = self.protocol_panel
        p.set_stages(self._n_stages)
        p.set_abort_armed(False)
        p.start_button.setEnabled(False)
        p.pause_button.setEnabled(True)
        p.pause_button.setChecked(False)
        self.connection.simulated.setEnabled(False)
        self.connection.speed.setEnabled(False)
        self.connection.connect_button.setEnabled(False)
        self.connection.light_fault.set("ok", "no amplifier fault", "no amplifier fault")
        self.log("info", f"starting {protocol.source} → {path}")
        bridge = _Bridge(self.signals)

        def work():
            from rig.session import acquire  # lazy: loaded when the operator uses it (window start-up time)

            try:
                cfg, lockstep, attrs, texts = config, False, {"operator_interface": "shakerlab gui"}, {}
                if simulated:
                    sim = self._ensure_sim()
                    cfg = config.with_addresses(sim.addresses)
                    lockstep = self._sim_speed is None
                    from sim_backend.config import DEFAULT_CONFIG_PATH  # lazy: loaded when the operator uses it (window start-up time)

                    attrs.update(simulated=True, seed=self.seed)
                    texts["simulator_toml"] = DEFAULT_CONFIG_PATH.read_text()
                self._loop_args = (cfg, protocol, lockstep)
                outcome = acquire(cfg, protocol, path, lockstep=lockstep, observers=[self.live, bridge],
                                  on_runner=self._got_runner, attrs=attrs, texts=texts)
                self.signals.finished.emit(outcome)
            except Exception as exc:  # noqa: BLE001 - connection errors etc.: nothing moved
                msg = str(exc) if isinstance(exc, UserFacingError) else f"{type(exc).__name__}: {exc}"
                self.signals.failed.emit(msg)

        self._run_thread = threading.Thread(target=work, name="gui-run")
        self._run_thread.start()
        self.statusBar().showMessage(f"running → {path}")
        return True

    def _got_runner(self, runner) -> None:
        """Called by acquire (worker thread) before the run starts."""
        self._runner = runner
        for _ in range(min(self._abort_presses, 2)):
            runner.abort("operator pressed ABORT (GUI)")

    def abort(self) -> None:
        """First press: ramp to zero and stop; second press: cut the output at once."""
        if self.loop_running():       # the closed loop's added stages: its runner ramps down (again: cuts)
            self.log("warning", "ABORT: cancelling the closed loop (a stage being recorded ramps down)")
            self.loop.cancel()
            return
        if not self.running():
            self.log("info", "ABORT: nothing is running")
            return
        self._abort_presses += 1
        runner = self._runner
        reason = "operator pressed ABORT (GUI)" if not self._close_pending else "window closed during the run"
        stopping = runner is not None and runner.state == "stopping"
        if runner is not None:
            runner.abort(reason)
        if stopping:  # the runner cuts at once when an abort comes during a stop (trip, error, abort)
            self.log("warning", "ABORT during the ramp-down: cutting the output at once")
        elif self._abort_presses == 1:
            self.log("warning", "ABORT: ramping the output to zero (press again to cut at once)")
            self.protocol_panel.set_abort_armed(True)
        else:
            self.log("warning", "ABORT pressed again: cutting the output at once")

    def _pause_toggled(self, on: bool) -> None:
        runner = self._runner
        if runner is None:  # not started yet: nothing to pause
            button = self.protocol_panel.pause_button
            button.blockSignals(True)
            button.setChecked(False)
            button.blockSignals(False)
            return
        if on:
            runner.pause()
            self.protocol_panel.pause_button.setText("Resume")
        else:
            runner.resume()
            self.protocol_panel.pause_button.setText("Pause")

    # -- runner notifications (GUI thread) ------------------------------------------------------------
    def _on_run_started(self, info) -> None:
        ids = info.get("identities", {})
        self.connection.show_identities(ids)
        settings = info.get("settings", {})
        self.connection.show_addresses({k: v.get("address", "—") for k, v in settings.items()})
        self.connection.light_connected.set("ok", "instruments identified and prepared")

    def _on_state(self, state: str) -> None:
        if state == "paused":
            self.protocol_panel.stage_label.setText(f"{self.live.stage or 'rest'} — paused (output at zero)")

    def _on_stage_begun(self, name, settings, index) -> None:
        self._stage_t0 = index / self.live.fs

    def _on_stage_ended(self, name, status, summary) -> None:
        p = self.protocol_panel
        p.progress.setValue(min(p.progress.maximum(), len(self.live.stages_done)))
        if name == "linear" and self.live.linear is not None:
            self.log("info", f"linear step: {self.live.linear.text()}")
            p.linear_label.setText(f"linear step: {self.live.linear.text()}")
            self.plots.p_loop.setTitle(LOOP_TITLE)
        elif name == "linear" and self.live.linear_error:
            self.log("warning", self.live.linear_error)

    def _end_of_run_ui(self) -> None:
        p = self.protocol_panel
        p.start_button.setEnabled(True)
        p.pause_button.setEnabled(False)
        p.pause_button.setChecked(False)
        p.pause_button.setText("Pause")
        p.set_abort_armed(False)
        self.connection.simulated.setEnabled(True)
        self.connection.speed.setEnabled(self.connection.simulated.isChecked())
        self.connection.connect_button.setEnabled(True)
        self._runner = None

    def _on_finished(self, outcome) -> None:
        if self._run_thread is not None:
            self._run_thread.join(timeout=5)
        self.last_outcome = outcome
        self._end_of_run_ui()
        self._redraw()
        self._update_status()
        if outcome.status == "error":
            self.connection.light_connected.set("bad", outcome.reason)
        p = self.protocol_panel
        p.stage_label.setText(f"run {outcome.status}" + (f": {outcome.reason}" if outcome.reason else ""))
        p.drive_label.setText(f"{outcome.run_time_s:.1f} s of rig time, {outcome.n_samples} samples per channel, "
                              f"{outcome.samples_lost} lost; file {outcome.path.name}")
        self.statusBar().showMessage(f"run {outcome.status}: {outcome.path}")
        if self._close_pending:
            self.close()
            return
        self.loop_panel.diagnose_button.setEnabled(outcome.status == "complete")
        if outcome.status == "complete" and self.loop_panel.enabled.isChecked():
            self.start_loop()
            return
        if outcome.status == "complete" and self.auto_reconstruct:
            truth = self.sim.world.truth() if self._run_simulated and self.sim is not None else None
            self.open_run(outcome.path, truth=truth)
        elif outcome.status != "complete":
            self.results.clear(f"run {outcome.status} ({outcome.reason}): {outcome.path}. Open it to reconstruct "
                               "from the stages it holds.")
            self.results_path = outcome.path
            self.results.reconstruct_button.setEnabled(True)

    def _on_failed(self, message: str) -> None:
        if self._run_thread is not None:
            self._run_thread.join(timeout=5)
        self._end_of_run_ui()
        self.connection.light_connected.set("bad", message)
        self.protocol_panel.stage_label.setText("run not started")
        self._error_box(f"run failed: {message}")
        if self._close_pending:
            self.close()

    # -- closed loop ----------------------------------------------------------------------------------
    def start_loop(self) -> bool:
        """Diagnose the last run and record the stages that decide into it (rig/gui/loop_panel.py)."""
        if self.running() or (self.loop is not None and self.loop.running()):
            return False
        if self.last_outcome is None or self.last_outcome.status != "complete" or self._loop_args is None:
            self.log("info", "closed loop: no complete run to diagnose")
            return False
        cfg, protocol, lockstep = self._loop_args
        if self._run_simulated:
            cfg = cfg.with_addresses(self._ensure_sim().addresses)
        self.loop = LoopController(self.loop_panel, self.last_outcome.path, cfg, protocol, lockstep=lockstep,
                                   observers=[self.live, _Bridge(self.signals)], on_runner=self._got_runner,
                                   diagnose=self.loop_diagnose, parent=self)
        self.loop.finished.connect(self._on_loop_finished)
        self.log("info", f"closed loop: diagnosing {self.last_outcome.path}")
        self.loop.start()
        return True

    def _on_loop_finished(self, result) -> None:
        if self._close_pending:
            self.close()
            return
        if result is None:
            self._error_box(f"closed loop failed: {self.loop.error}")
            return
        self.log("info", f"closed loop stopped ({result.stop}): {result.stop_reason}")
        if self.auto_reconstruct:
            self.open_run(self.last_outcome.path)

    # -- results --------------------------------------------------------------------------------------
    def open_run(self, path, reconstruct: bool = False, truth: dict | None = None, law=None) -> bool:
        """Show a run file's result (stored, or reconstructed now) in the Results tab (worker thread).

        ``truth``: the simulated specimen's parameters, shown beside the identified ones.
        ``law``: a component test's law JSON as the baseline (its mass and support fitted on the run)."""
        if path is None:
            return False
        if self._recon_thread is not None and self._recon_thread.is_alive():
            self.log("warning", "a reconstruction is already running")
            return False
        path = Path(path)
        self.results_path = path
        self.results.clear(f"reading {path} and reconstructing the governing equation…" if reconstruct else
                           f"reading {path}…")
        self.results.reconstruct_button.setEnabled(False)
        self.results.open_button.setEnabled(False)
        self.results.law_button.setEnabled(False)
        self.results.diagnose_button.setEnabled(False)
        self.tabs.setCurrentWidget(self.results)

        def work():
            from rig.gui.results import view_of_run_file  # lazy: loaded when the operator uses it (window start-up time)

            try:
                self.signals.result_ready.emit(view_of_run_file(path, reconstruct=reconstruct, truth=truth, law=law))
            except Exception as exc:  # noqa: BLE001 - shown to the operator
                msg = str(exc) if isinstance(exc, UserFacingError) else f"{type(exc).__name__}: {exc}"
                self.signals.result_failed.emit(msg)

        self._recon_thread = threading.Thread(target=work, name="gui-reconstruct", daemon=True)
        self._recon_thread.start()
        return True

    def _choose_law(self) -> None:
        law, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Component law (JSON)", str(Path.cwd()), "JSON (*.json)")
        if law:
            self.open_run(self.results_path, law=law)

    def _on_result(self, view) -> None:
        self.last_view = view
        self.results.show_view(view)
        self.results.reconstruct_button.setEnabled(True)
        self.results.open_button.setEnabled(True)
        self.results.law_button.setEnabled("loop_title" not in view.labels)   # a structure's run (not a component test)
        can = "loop_title" not in view.labels and not self._diagnosing()
        self.results.diagnose_button.setEnabled(can)
        self.diagnosis.start_button.setEnabled(can)
        self.log("info", f"result of {view.source}: {view.origin}")

    def _on_result_failed(self, message: str) -> None:
        self.results.clear(f"no result: {message}")
        self.results.reconstruct_button.setEnabled(self.results_path is not None)
        self.results.open_button.setEnabled(True)
        self.results.law_button.setEnabled(self.results_path is not None)
        self._error_box(message)

    # -- diagnosis ------------------------------------------------------------------------------------------
    def _diagnosing(self) -> bool:
        return self._diag_thread is not None and self._diag_thread.is_alive()

    def diagnose_run(self, path=None, baseline=None, candidates=None) -> bool:
        """Diagnose a recorded run (default: the one shown in the Results tab) in the ``gui-diagnose``
        worker thread, which runs ``recon.diagnose`` in a child process (rig.gui.diagnosis): progress in
        the Diagnosis tab, *Cancel* stops it at once. ``baseline``: "paper", "linear" or a model JSON
        (default: the tab's choice); ``candidates``: catalog ids (default: the whole catalog)."""
        path = Path(path) if path is not None else self.results_path
        if path is None:
            self._error_box("diagnose: open a recorded run first")
            return False
        if self._diagnosing():
            self.log("warning", "a diagnosis is already running")
            return False
        baseline = baseline or self.diagnosis.baseline.currentText()
        self.diagnosis_state = "running"
        self.diagnosis.set_running(str(path), str(baseline))
        self.results.diagnose_button.setEnabled(False)
        self.tabs.setCurrentWidget(self.diagnosis)
        s = self.signals
        job = DiagnosisJob(path, baseline, candidates, on_progress=s.diagnosis_progress.emit)
        self._diag_job = job

        def work():
            try:
                s.diagnosis_ready.emit(job.run())
            except Cancelled:
                s.diagnosis_cancelled.emit()
            except Exception as exc:  # noqa: BLE001 - shown to the operator
                if job.cancelled:
                    s.diagnosis_cancelled.emit()
                else:
                    s.diagnosis_failed.emit(str(exc) if isinstance(exc, UserFacingError) else
                                            f"{type(exc).__name__}: {exc}")

        self._diag_thread = threading.Thread(target=work, name="gui-diagnose", daemon=True)
        self._diag_thread.start()
        self.log("info", f"diagnosing {path} against the {baseline} baseline")
        return True

    def cancel_diagnosis(self) -> None:
        if self._diag_job is not None and self._diagnosing():
            self.diagnosis.step_label.setText("cancelling…")
            self._diag_job.cancel()

    def _diagnosis_ended(self) -> None:
        if self._diag_thread is not None:
            self._diag_thread.join(timeout=5)
        self.results.diagnose_button.setEnabled(self.results_path is not None)

    def _on_diagnosis(self, view) -> None:
        self._diagnosis_ended()
        self.last_diagnosis = view
        self.diagnosis_state = "done"
        self.diagnosis.show_view(view)
        self.diagnosis.set_stopped(f"done in {view.seconds:.0f} s", True)
        self.log("info", f"diagnosis of {view.source}: {view.sentence()}")

    def _on_diagnosis_failed(self, message: str) -> None:
        self._diagnosis_ended()
        self.diagnosis_state = "failed"
        self.diagnosis.set_stopped(f"failed: {message}", True)
        self._error_box(message)

    def _on_diagnosis_cancelled(self) -> None:
        self._diagnosis_ended()
        self.diagnosis_state = "cancelled"
        self.diagnosis.set_stopped("cancelled: nothing was stored", True)
        self.log("info", "diagnosis cancelled")

    # -- live redraw (GUI thread, FPS per second) ---------------------------------------------------------
    def _redraw(self) -> None:
        self.ticks += 1
        live = self.live
        if self.running():
            lag = live.lag(self._run_speed)
            if not self.throttled and lag > LAG_THROTTLE_S:
                self.throttled = True
                self.log("warning", f"acquisition {lag:.2f} s behind real time: plots redraw at {FPS // THROTTLE} "
                                    "frames/s until it catches up")
            elif self.throttled and lag < LAG_RESUME_S:
                self.throttled = False
                self.log("info", "acquisition caught up: plots back at full rate")
            if self.throttled and self.ticks % THROTTLE:
                self.throttled_ticks += 1
                return
        t_start = time.perf_counter()
        t, xb, xt = live.traces(TRACE_SECONDS)
        set_series(self.plots.c_base, t, xb)
        set_series(self.plots.c_tip, t, xt)
        set_series(self.plots.c_rel, t, xt - xb)
        if self.running():
            loop = live.live_loop()
            if loop is not None:
                y, fn = loop
                self.plots.c_loop.setData(y, fn)
        if self.frames % 5 == 0:
            for stage, (ts, amp) in live.amplitude_series().items():
                set_series(self.plots.amplitude_curve(stage), ts, amp)
            self.plots.show_control(live.control_series())
            self._update_status()
        self.frames += 1
        dt = time.perf_counter() - t_start
        self.redraw_seconds += dt
        self.redraw_times.append(dt)
        if len(self.redraw_times) > 1000:
            del self.redraw_times[:500]

    def _update_status(self) -> None:
        live, d = self.live, self.live.drive
        running = self.running()
        p = self.protocol_panel
        if running:
            stage = live.stage
            if live.state == "paused":
                p.stage_label.setText(f"{stage or 'rest'} — paused (output at zero)")
            elif live.state == "stopping":
                p.stage_label.setText("stopping: ramping the output to zero")
            elif stage is not None:
                el = d.run_time - (self._stage_t0 or 0.0)
                p.stage_label.setText(f"stage {stage} ({len(live.stages_done) + 1}/{self._n_stages}), {el:.1f} s")
            else:
                p.stage_label.setText("rest between stages (output off)")
            lag = live.lag(self._run_speed)
            p.drive_label.setText(f"run time {d.run_time:.1f} s; drive {d.amplitude_vpp:.3f} Vpp at "
                                  f"{d.frequency_hz:.3f} Hz" + (f"; amplifier {d.current_a:.3f} A"
                                                                if d.current_a is not None else "")
                                  + (f"; acquisition {lag:.2f} s behind" if lag > LAG_RESUME_S else ""))
        c = self.connection
        c.light_output.set("warn" if running and d.output else "off", "generator output on" if d.output else "")
        if live.max_faults:
            c.light_fault.set("bad", "amplifier faults seen: " + ", ".join(sorted(live.max_faults)),
                              "amplifier FAULT")
        runner = self._runner
        inst = getattr(runner, "inst", None)
        if "watchdog" in live.max_faults:
            c.light_watchdog.set("bad", "the amplifier's comms watchdog tripped")
        elif running and inst is not None and (inst.heartbeat_error is not None or inst.heartbeat_stalled):
            c.light_watchdog.set("bad", f"heartbeat stopped: {inst.heartbeat_error or 'runner stalled'}")
        elif running and inst is not None and live.blocks:
            c.light_watchdog.set("ok", "heartbeat feeding the amplifier's watchdog")
        else:
            c.light_watchdog.set("off", "no heartbeat (not running)")

    # -- closing ------------------------------------------------------------------------------------------
    def closeEvent(self, event) -> None:  # noqa: N802 - Qt name
        if self.loop_running():
            self._close_pending = True
            self.loop.cancel()
            event.ignore()
            return
        if self.running():
            if not self._close_pending:
                self._close_pending = True
                self.log("warning", "window closed during the run: ramping the output to zero before closing")
                if self._abort_presses == 0:
                    self.abort()
            event.ignore()
            return
        self.timer.stop()
        self.cancel_diagnosis()
        self.stop_sim()
        event.accept()

    def shutdown(self, timeout: float = 10.0) -> None:
        """Abort any run and wait for it (application exit without a close event)."""
        if self.loop_running():
            self.loop.cancel()
            self.loop.join(timeout)
        if self.running():
            self._close_pending = True
            if self._runner is not None:
                self._runner.abort("application quit during the run")
            self._run_thread.join(timeout)
        self.timer.stop()
        self.cancel_diagnosis()
        if self._diag_thread is not None:
            self._diag_thread.join(timeout)
        self.stop_sim()
