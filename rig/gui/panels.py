"""The window's panels: connection, protocol, live plots, results (widgets only, no run logic)."""
from __future__ import annotations

import math
import re

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets

from rig.gui.diagnosis import overlay_arrays
from rig.gui.results import STRUCTURE_LABELS
from shakerlab.words import nrmse_text

STAGE_COLORS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#17becf"]
LIGHT_COLORS = {"off": "#9a9a9a", "ok": "#21a336", "warn": "#e0a800", "bad": "#d62020"}
INSTRUMENTS = (("generator", "signal generator"), ("amplifier", "power amplifier"),
               ("sensor_base", "base sensor"), ("sensor_tip", "tip sensor"))

LOOP_WAITING = "Fn vs y (drawn once the linear step is known)"
CONTROL_WAITING = "sine control: base target vs achieved (stages given in base_amplitude_mm)"
LOOP_TITLE = "Fn = −x_tip'' − c_m y' − K_m y vs y"

BANNER_STYLES = {"green": ("#e3f4e5", "#1d7a2e"), "amber": ("#fff3d6", "#a86b00"), "red": ("#fbe1e1", "#b31b1b"),
                 "grey": ("#ececec", "#555555")}

pg.setConfigOptions(antialias=False, background="w", foreground="k")


def time_axis(plot, label: str) -> None:
    """A time axis in seconds, never rescaled to ms or ks (every time axis of the window reads s)."""
    plot.setLabel("bottom", label, units="s")
    plot.getAxis("bottom").enableAutoSIPrefix(False)


def wrap_terms(equation: str, width: int, indent: str = "    ") -> str:
    """The equation wrapped to ``width`` characters between its terms only: a continuation line
    starts with an operator (``+``, ``-``, ``=``), never inside a term such as ``- 300 |y'| z``. A
    term longer than the width stays whole on its own line."""
    out = []
    for line in equation.split("\n"):
        terms = re.split(r" (?=[+\-=] )", line)
        current = terms[0]
        for term in terms[1:]:
            if len(current) + 1 + len(term) <= width:
                current += " " + term
            else:
                out.append(current)
                current = indent + term
        out.append(current)
    return "\n".join(out)


class EquationView(QtWidgets.QPlainTextEdit):
    """The identified equation in a fixed-width font, wrapped between terms to the view's width."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setReadOnly(True)
        font = QtGui.QFontDatabase.systemFont(QtGui.QFontDatabase.FixedFont)
        font.setPointSize(9)
        self.setFont(font)
        self.setLineWrapMode(QtWidgets.QPlainTextEdit.NoWrap)
        self.equation = ""

    def columns(self) -> int:
        advance = max(1, QtGui.QFontMetrics(self.font()).horizontalAdvance("M"))
        return max(20, (self.viewport().width() - 8) // advance)

    def set_equation(self, equation: str) -> None:
        self.equation = equation
        self.setPlainText(wrap_terms(equation, self.columns()))

    def resizeEvent(self, event) -> None:  # noqa: N802 - Qt name
        super().resizeEvent(event)
        if self.equation:
            self.setPlainText(wrap_terms(self.equation, self.columns()))


class Banner(QtWidgets.QLabel):
    """A verdict as a coloured band with its one sentence: green, amber, red or grey."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setWordWrap(True)
        self.setTextInteractionFlags(QtCore.Qt.TextSelectableByMouse)
        self.level = ""
        self.set_verdict(None)

    def set_verdict(self, verdict: tuple | None) -> None:
        """``verdict`` = (level, sentence); None hides the band."""
        if verdict is None:
            self.level = ""
            self.setText("")
            self.setVisible(False)
            return
        self.level, sentence = verdict
        bg, fg = BANNER_STYLES.get(self.level, BANNER_STYLES["grey"])
        self.setStyleSheet(f"QLabel {{ background:{bg}; color:{fg}; border:1px solid {fg}; border-radius:4px; "
                           f"padding:6px; font-weight:bold; }}")
        self.setText(sentence)
        self.setVisible(True)


class Light(QtWidgets.QWidget):
    """A status light with a caption: off (grey), ok (green), warn (amber), bad (red)."""

    def __init__(self, caption: str, parent=None):
        super().__init__(parent)
        lay = QtWidgets.QHBoxLayout(self)
        lay.setContentsMargins(0, 0, 8, 0)
        self.dot = QtWidgets.QLabel()
        self.dot.setFixedSize(14, 14)
        self.caption = QtWidgets.QLabel(caption)
        lay.addWidget(self.dot)
        lay.addWidget(self.caption)
        self.state = ""
        self.set("off", "")

    def set(self, state: str, tip: str = "", caption: str | None = None) -> None:
        if caption is not None and caption != self.caption.text():
            self.caption.setText(caption)
        if state != self.state:
            self.state = state
            self.dot.setStyleSheet(f"background:{LIGHT_COLORS[state]}; border-radius:7px; border:1px solid #555;")
        self.setToolTip(tip)


class ConnectionPanel(QtWidgets.QGroupBox):
    """Rig config, simulated-rig switch, addresses, identity strings and status lights."""

    def __init__(self, parent=None):
        super().__init__("Connection", parent)
        form = QtWidgets.QGridLayout(self)
        self.simulated = QtWidgets.QCheckBox("simulated rig (started here, on loopback)")
        self.simulated.setChecked(True)
        self.speed = QtWidgets.QDoubleSpinBox()
        self.speed.setRange(0.0, 20.0)
        self.speed.setSingleStep(0.5)
        self.speed.setValue(1.0)
        self.speed.setToolTip("simulated time per wall time; 1 = real time, 0 = as fast as possible (lockstep)")
        self.config_path = QtWidgets.QLineEdit()
        self.config_path.setPlaceholderText("rig/default_rig.toml (shipped limits)")
        self.browse = QtWidgets.QPushButton("…")
        self.browse.setFixedWidth(28)
        self.connect_button = QtWidgets.QPushButton("Connect && identify")
        form.addWidget(self.simulated, 0, 0, 1, 3)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(QtWidgets.QLabel("speed"))
        row.addWidget(self.speed)
        row.addStretch(1)
        form.addLayout(row, 0, 3)
        form.addWidget(QtWidgets.QLabel("rig config"), 1, 0)
        form.addWidget(self.config_path, 1, 1, 1, 2)
        form.addWidget(self.browse, 1, 3, QtCore.Qt.AlignLeft)
        self.address = {}
        self.identity = {}
        for i, (key, label) in enumerate(INSTRUMENTS):
            form.addWidget(QtWidgets.QLabel(label), 2 + i, 0)
            self.address[key] = QtWidgets.QLabel("—")
            self.address[key].setTextInteractionFlags(QtCore.Qt.TextSelectableByMouse)
            self.identity[key] = QtWidgets.QLabel("")
            self.identity[key].setStyleSheet("color:#444;")
            self.identity[key].setTextInteractionFlags(QtCore.Qt.TextSelectableByMouse)
            form.addWidget(self.address[key], 2 + i, 1)
            form.addWidget(self.identity[key], 2 + i, 2, 1, 2)
        lights = QtWidgets.QHBoxLayout()
        self.light_connected = Light("connected")
        self.light_fault = Light("amplifier fault")
        self.light_watchdog = Light("watchdog")
        self.light_output = Light("output on")
        for w in (self.light_connected, self.light_fault, self.light_watchdog, self.light_output):
            lights.addWidget(w)
        lights.addStretch(1)
        lights.addWidget(self.connect_button)
        form.addLayout(lights, 6, 0, 1, 4)
        form.setColumnStretch(2, 1)
        self.simulated.toggled.connect(self._sim_toggled)

    def _sim_toggled(self, on: bool) -> None:
        self.speed.setEnabled(on)

    def show_addresses(self, addresses: dict) -> None:
        for key, _ in INSTRUMENTS:
            self.address[key].setText(str(addresses.get(key, "—")))

    def show_identities(self, identities: dict) -> None:
        for key, _ in INSTRUMENTS:
            self.identity[key].setText(str(identities.get(key, "")))


class ProtocolPanel(QtWidgets.QGroupBox):
    """Protocol file and editor, start / pause / ABORT, stage and progress, limits in force."""

    def __init__(self, parent=None):
        super().__init__("Protocol", parent)
        lay = QtWidgets.QVBoxLayout(self)
        top = QtWidgets.QHBoxLayout()
        self.source = QtWidgets.QLabel("rig/default_protocol.toml")
        self.source.setStyleSheet("color:#444;")
        self.load_button = QtWidgets.QPushButton("Load…")
        self.save_button = QtWidgets.QPushButton("Save as…")
        top.addWidget(self.source, 1)
        top.addWidget(self.load_button)
        top.addWidget(self.save_button)
        lay.addLayout(top)
        self.editor = QtWidgets.QPlainTextEdit()
        font = QtGui.QFontDatabase.systemFont(QtGui.QFontDatabase.FixedFont)
        font.setPointSize(9)
        self.editor.setFont(font)
        self.editor.setLineWrapMode(QtWidgets.QPlainTextEdit.NoWrap)
        lay.addWidget(self.editor, 1)
        buttons = QtWidgets.QHBoxLayout()
        self.start_button = QtWidgets.QPushButton("Start")
        self.pause_button = QtWidgets.QPushButton("Pause")
        self.pause_button.setCheckable(True)
        self.pause_button.setEnabled(False)
        for b in (self.start_button, self.pause_button):
            b.setMinimumHeight(34)
            buttons.addWidget(b)
        lay.addLayout(buttons)
        self.abort_button = QtWidgets.QPushButton("ABORT")
        self.abort_button.setMinimumHeight(56)
        self.abort_button.setToolTip("first press: ramp the output to zero and stop; second press: cut at once")
        self.abort_button.setStyleSheet(
            "QPushButton { background:#c8102e; color:white; font-size:20px; font-weight:bold; border-radius:6px; }"
            "QPushButton:pressed { background:#8e0b20; }")
        lay.addWidget(self.abort_button)
        self.stage_label = QtWidgets.QLabel("idle")
        self.stage_label.setStyleSheet("font-weight:bold;")
        self.drive_label = QtWidgets.QLabel("")
        self.linear_label = QtWidgets.QLabel("linear step: not yet known")
        self.linear_label.setToolTip("K_m and c_m from the fundamental of the linear stage (rig.gui.live_state)")
        self.progress = QtWidgets.QProgressBar()
        self.set_idle()
        self.limits_label = QtWidgets.QLabel("")
        self.limits_label.setWordWrap(True)
        self.limits_label.setStyleSheet("color:#444;")
        for w in (self.stage_label, self.drive_label, self.linear_label, self.progress, self.limits_label):
            lay.addWidget(w)

    def set_idle(self) -> None:
        """No run yet: the bar says so instead of counting stages of a protocol not started."""
        self.progress.setRange(0, 1)
        self.progress.setValue(0)
        self.progress.setFormat("no run yet")

    def set_stages(self, n: int) -> None:
        self.progress.setRange(0, n)
        self.progress.setValue(0)
        self.progress.setFormat("%v / %m stages")

    def set_abort_armed(self, armed: bool) -> None:
        """After a first press during a run, the button offers the immediate cut."""
        self.abort_button.setText("CUT OUTPUT NOW" if armed else "ABORT")

    def show_limits(self, limits: dict) -> None:
        self.limits_label.setText(
            "Limits in force: generator ≤ {:g} Vpp, gain ≤ {:g}, base ≤ {:.3g} mm, tip ≤ {:.3g} mm, "
            "current ≤ {:g} A; ramps {:g} Vpp/s, abort ramp {:g} s".format(
                limits["max_generator_vpp"], limits["max_amplifier_gain"], limits["max_base_displacement_m"] * 1e3,
                limits["max_tip_displacement_m"] * 1e3, limits["max_amplifier_current_a"],
                limits["ramp_rate_vpp_per_s"], limits["abort_ramp_s"]))


def _curve(plot, color, name=None, width=1):
    c = plot.plot(pen=pg.mkPen(color, width=width), name=name)
    c.setDownsampling(auto=True, method="peak")
    c.setClipToView(True)
    return c


class LivePlots(pg.GraphicsLayoutWidget):
    """Base and tip traces, relative displacement, live nonlinear restoring-force loop, amplitude per stage."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.p_traces = self.addPlot(row=0, col=0, title="base and tip displacement (from rest)")
        self.p_traces.addLegend(offset=(5, 5))
        self.c_base = _curve(self.p_traces, "#1f77b4", "x_base")
        self.c_tip = _curve(self.p_traces, "#d62728", "x_tip")
        self.p_rel = self.addPlot(row=1, col=0, title="relative displacement y = x_tip − x_base")
        self.c_rel = _curve(self.p_rel, "#2ca02c")
        for p in (self.p_traces, self.p_rel):
            p.setLabel("left", "displacement", units="m")
            time_axis(p, "run time")
            p.showGrid(x=True, y=True, alpha=0.2)
        self.p_rel.setXLink(self.p_traces)
        self.p_loop = self.addPlot(row=0, col=1, title=LOOP_WAITING)
        self.p_loop.setLabel("left", "Fn", units="m/s²")
        self.p_loop.setLabel("bottom", "y", units="m")
        self.p_loop.showGrid(x=True, y=True, alpha=0.2)
        self.c_loop = self.p_loop.plot(pen=pg.mkPen("#9467bd", width=2))
        self.p_amp = self.addPlot(row=1, col=1, title="response amplitude, per stage")
        self.p_amp.setLabel("left", "(max y − min y) / 2", units="m")
        time_axis(self.p_amp, "run time")
        self.p_amp.showGrid(x=True, y=True, alpha=0.2)
        self.p_amp.addLegend(offset=(5, 5))
        self.c_amp: dict = {}
        # closed-loop sine control (rig.sine_control): base target against achieved, per window; in
        # the layout only while the protocol gives base targets (set_control_visible)
        self.p_ctrl = pg.PlotItem(title=CONTROL_WAITING)
        self.p_ctrl.setLabel("left", "base amplitude", units="m")
        time_axis(self.p_ctrl, "run time")
        self.p_ctrl.showGrid(x=True, y=True, alpha=0.2)
        self.p_ctrl.addLegend(offset=(5, 5))
        self.c_target = self.p_ctrl.plot(pen=pg.mkPen("#7f7f7f", width=2, style=QtCore.Qt.DashLine), name="target")
        self.c_achieved = self.p_ctrl.plot(pen=None, symbol="o", symbolSize=4, symbolBrush="#1f77b4",
                                           symbolPen=None, name="achieved")

    def control_visible(self) -> bool:
        return self.p_ctrl in self.ci.items

    def set_control_visible(self, on: bool) -> None:
        """The sine-control plot takes its row only for a closed-loop protocol (base targets)."""
        if on and not self.control_visible():
            self.addItem(self.p_ctrl, row=2, col=0, colspan=2)
        elif not on and self.control_visible():
            self.removeItem(self.p_ctrl)

    def show_control(self, series) -> None:
        """``series`` = LiveData.control_series(): target (line) against achieved (points)."""
        if series is None:
            return
        self.set_control_visible(True)
        t, target, achieved, err = series
        self.c_target.setData(t, target, connect="finite")
        self.c_achieved.setData(t, achieved)
        self.p_ctrl.setTitle(f"sine control: base target vs achieved (last window {err[-1]:+.2f} dB)")

    def reset(self) -> None:
        self.c_target.setData([], [])
        self.c_achieved.setData([], [])
        self.p_ctrl.setTitle(CONTROL_WAITING)
        for c in (self.c_base, self.c_tip, self.c_rel, self.c_loop):
            c.setData([], [])
        for c in self.c_amp.values():
            self.p_amp.removeItem(c)
        self.c_amp.clear()
        self.p_amp.legend.clear()
        self.p_loop.setTitle(LOOP_WAITING)

    def amplitude_curve(self, stage: str):
        c = self.c_amp.get(stage)
        if c is None:
            color = STAGE_COLORS[len(self.c_amp) % len(STAGE_COLORS)]
            c = self.p_amp.plot(pen=pg.mkPen(color, width=2), symbol="o", symbolSize=3,
                                symbolBrush=color, symbolPen=None, name=stage)
            self.c_amp[stage] = c
        return c


class ResultsPanel(QtWidgets.QWidget):
    """Equation, parameter table, measured-vs-simulated overlay, hysteresis loop, diagnosis (if any)."""

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QtWidgets.QVBoxLayout(self)
        top = QtWidgets.QHBoxLayout()
        self.open_button = QtWidgets.QPushButton("Open run file…")
        self.reconstruct_button = QtWidgets.QPushButton("Reconstruct again")
        self.reconstruct_button.setEnabled(False)
        self.law_button = QtWidgets.QPushButton("Component law as baseline…")
        self.law_button.setToolTip("a law from a component test of the same specimen (reconstruct --save-model of a "
                                   "constitutive run): its mass and support are fitted on this run")
        self.law_button.setEnabled(False)
        self.diagnose_button = QtWidgets.QPushButton("Diagnose…")
        self.diagnose_button.setToolTip("locate and name what the model leaves out (recon.diagnose, in the "
                                        "Diagnosis tab; runs in the background and can be cancelled)")
        self.diagnose_button.setEnabled(False)
        self.header = QtWidgets.QLabel("No result yet: finish a run, or open a recorded run file.")
        self.header.setWordWrap(True)
        top.addWidget(self.header, 1)
        top.addWidget(self.open_button)
        top.addWidget(self.reconstruct_button)
        top.addWidget(self.law_button)
        top.addWidget(self.diagnose_button)
        lay.addLayout(top)
        self.banner = Banner()
        lay.addWidget(self.banner)
        split = QtWidgets.QSplitter(QtCore.Qt.Horizontal)
        left = QtWidgets.QWidget()
        ll = QtWidgets.QVBoxLayout(left)
        ll.setContentsMargins(0, 0, 0, 0)
        ll.addWidget(QtWidgets.QLabel("Identified equation (per unit mass)"))
        self.equation = EquationView()
        self.equation.setMaximumHeight(110)
        ll.addWidget(self.equation)
        ll.addWidget(QtWidgets.QLabel("Parameters"))
        self.table = QtWidgets.QTableWidget(0, 4)
        self.table.setHorizontalHeaderLabels(["parameter", "identified", "unit", "true (simulator)"])
        self.table.horizontalHeader().setSectionResizeMode(QtWidgets.QHeaderView.ResizeToContents)
        self.table.horizontalHeader().setStretchLastSection(True)
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.NoEditTriggers)
        ll.addWidget(self.table, 1)
        self.diagnosis_box = QtWidgets.QGroupBox("Diagnosis")
        dl = QtWidgets.QVBoxLayout(self.diagnosis_box)
        self.diagnosis = QtWidgets.QPlainTextEdit()
        self.diagnosis.setReadOnly(True)
        dl.addWidget(self.diagnosis)
        self.diagnosis_box.setVisible(False)
        ll.addWidget(self.diagnosis_box)
        split.addWidget(left)
        self.plots = pg.GraphicsLayoutWidget()
        self.p_overlay = self.plots.addPlot(row=0, col=0, title="validation: measured vs simulated")
        self.p_overlay.addLegend(offset=(5, 5))
        self.p_overlay.setLabel("left", "y", units="m")
        time_axis(self.p_overlay, "stage time")
        self.p_overlay.showGrid(x=True, y=True, alpha=0.2)
        self.c_meas = _curve(self.p_overlay, "#555555", "measured")
        self.c_sim = _curve(self.p_overlay, "#d62728", "simulated (identified model)")
        self.p_loop = self.plots.addPlot(row=1, col=0, title="hysteresis loop z vs y")
        self.p_loop.addLegend(offset=(5, 5))
        self.p_loop.setLabel("left", "z", units="m/s²")
        self.p_loop.setLabel("bottom", "y", units="m")
        self.p_loop.showGrid(x=True, y=True, alpha=0.2)
        self.c_zmeas = self.p_loop.plot(pen=None, symbol="o", symbolSize=2, symbolBrush=(120, 120, 120, 90),
                                        symbolPen=None, name=STRUCTURE_LABELS["measured_name"])
        self.c_zsim = self.p_loop.plot(pen=pg.mkPen("#9467bd", width=2), name="identified model")
        split.addWidget(self.plots)
        split.setSizes([430, 800])
        lay.addWidget(split, 1)

    def clear(self, message: str) -> None:
        self.header.setText(message)
        self.banner.set_verdict(None)
        self.equation.set_equation("")
        self.table.setRowCount(0)
        for c in (self.c_meas, self.c_sim, self.c_zmeas, self.c_zsim):
            c.setData([], [])
        self.diagnosis_box.setVisible(False)

    def show_view(self, view) -> None:
        if view.validation_stage is None:
            nrmse = ""
        elif math.isinf(view.nrmse):
            nrmse = f"; <b>the model diverges</b> when simulated on stage '{view.validation_stage}'"
        else:
            nrmse = (f"; the overlay below (the model simulated here from rest on stage "
                     f"'{view.validation_stage}'): NRMSE {nrmse_text(view.nrmse)}")
        notes = "".join(f"<br><i>{n}</i>" for n in view.notes)
        self.header.setText(f"<b>{view.source}</b> (run {view.status}): {view.origin}{nrmse}{notes}")
        self.banner.set_verdict(view.verdict)
        labels = {**STRUCTURE_LABELS, **(getattr(view, "labels", None) or {})}
        self.p_overlay.setLabel("left", labels["overlay"][0], units=labels["overlay"][1])
        self.p_loop.setLabel("left", labels["loop_left"][0], units=labels["loop_left"][1])
        self.p_loop.setLabel("bottom", labels["loop_bottom"][0], units=labels["loop_bottom"][1])
        for sample, label in self.p_loop.legend.items:
            if sample.item is self.c_zmeas:
                label.setText(labels["measured_name"])
        self.equation.set_equation(view.equation)
        has_truth = any(r[3] is not None for r in view.parameters)
        self.table.setColumnHidden(3, not has_truth)
        self.table.setRowCount(len(view.parameters))
        for i, (name, value, unit, true) in enumerate(view.parameters):
            cells = [name, f"{value:.6g}", unit, "" if true is None else f"{true:.6g}"]
            for j, text in enumerate(cells):
                item = QtWidgets.QTableWidgetItem(text)
                if j in (1, 3):
                    item.setTextAlignment(QtCore.Qt.AlignRight | QtCore.Qt.AlignVCenter)
                self.table.setItem(i, j, item)
        if view.overlay is not None:
            t, ym, ys = view.overlay
            t = t - t[0]
            self.c_meas.setData(t, ym)
            self.c_sim.setData(t, ys)
        else:
            self.c_meas.setData([], [])
            self.c_sim.setData([], [])
        if view.loop is not None:
            y, z = view.loop
            last = labels["loop_last_third"]
            keep = slice(max(0, y.size - y.size // 3), None) if last else slice(None)   # the last third: steady state
            self.c_zsim.setData(y[keep], z[keep])
            self.p_loop.setTitle(f"{labels['loop_title']}: model simulated on stage '{view.loop_stage}'"
                                 + (" (last third)" if last else ""))
        else:
            self.c_zsim.setData([], [])
            self.p_loop.setTitle(labels["loop_title"])
        legend = self.p_loop.legend
        in_legend = any(sample.item is self.c_zmeas for sample, _ in legend.items)
        if view.measured_loop is not None:
            y, z = view.measured_loop
            step = max(1, y.size // 3000)
            self.c_zmeas.setData(y[::step], z[::step])
            if not in_legend:
                legend.addItem(self.c_zmeas, labels["measured_name"])
        else:
            self.c_zmeas.setData([], [])
            if in_legend:        # nothing drawn: no legend entry that names a quantity not shown
                legend.removeItem(self.c_zmeas)
        self.diagnosis_box.setVisible(view.diagnosis is not None)
        self.diagnosis.setPlainText(view.diagnosis or "")


class DiagnosisPanel(QtWidgets.QWidget):
    """A diagnosis of a recorded run: its progress (step, share, elapsed, estimate) and Cancel while it
    runs; then the verdict, the named physics with its fitted size, the NRMSE per stage before and
    after, and the recorded, baseline and augmented output on the held-out samples."""

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QtWidgets.QVBoxLayout(self)
        top = QtWidgets.QHBoxLayout()
        self.header = QtWidgets.QLabel("No diagnosis yet: open a recorded run in the Results tab and press Diagnose.")
        self.header.setWordWrap(True)
        self.baseline = QtWidgets.QComboBox()
        self.baseline.addItems(["paper", "linear"])
        self.baseline.setToolTip("paper: the model reconstruct finds on this run's fitting samples; linear: "
                                 "the linear step alone")
        self.start_button = QtWidgets.QPushButton("Diagnose")
        self.start_button.setEnabled(False)
        self.cancel_button = QtWidgets.QPushButton("Cancel")
        self.cancel_button.setEnabled(False)
        top.addWidget(self.header, 1)
        top.addWidget(QtWidgets.QLabel("baseline"))
        top.addWidget(self.baseline)
        top.addWidget(self.start_button)
        top.addWidget(self.cancel_button)
        lay.addLayout(top)
        prog = QtWidgets.QHBoxLayout()
        self.progress = QtWidgets.QProgressBar()
        self.progress.setRange(0, 1000)
        self.progress.setValue(0)
        self.progress.setTextVisible(False)
        self.step_label = QtWidgets.QLabel("")
        prog.addWidget(self.progress, 1)
        prog.addWidget(self.step_label, 2)
        lay.addLayout(prog)
        self.banner = Banner()
        lay.addWidget(self.banner)
        split = QtWidgets.QSplitter(QtCore.Qt.Horizontal)
        left = QtWidgets.QWidget()
        ll = QtWidgets.QVBoxLayout(left)
        ll.setContentsMargins(0, 0, 0, 0)
        ll.addWidget(QtWidgets.QLabel("Named physics (fitted on this run)"))
        self.named = QtWidgets.QTableWidget(0, 4)
        self.named.setHorizontalHeaderLabels(["effect", "fitted size", "held-out NRMSE before → after", "meaning"])
        for t in (self.named,):
            t.horizontalHeader().setSectionResizeMode(QtWidgets.QHeaderView.ResizeToContents)
            t.horizontalHeader().setStretchLastSection(True)
            t.verticalHeader().setVisible(False)
            t.setEditTriggers(QtWidgets.QAbstractItemView.NoEditTriggers)
        ll.addWidget(self.named, 1)
        ll.addWidget(QtWidgets.QLabel("NRMSE per stage: baseline as given → augmented model"))
        self.stages = QtWidgets.QTableWidget(0, 3)
        self.stages.setHorizontalHeaderLabels(["stage", "before", "after"])
        self.stages.horizontalHeader().setSectionResizeMode(QtWidgets.QHeaderView.ResizeToContents)
        self.stages.horizontalHeader().setStretchLastSection(True)
        self.stages.verticalHeader().setVisible(False)
        self.stages.setEditTriggers(QtWidgets.QAbstractItemView.NoEditTriggers)
        ll.addWidget(self.stages, 1)
        self.details = QtWidgets.QPlainTextEdit()
        self.details.setReadOnly(True)
        self.details.setMaximumHeight(130)
        ll.addWidget(self.details)
        split.addWidget(left)
        self.plots = pg.GraphicsLayoutWidget()
        self.p_overlay = self.plots.addPlot(row=0, col=0, title="held-out samples: recorded, baseline, augmented")
        self.p_overlay.addLegend(offset=(5, 5))
        self.p_overlay.setLabel("left", "y", units="m")
        time_axis(self.p_overlay, "time in the held-out part")
        self.p_overlay.showGrid(x=True, y=True, alpha=0.2)
        self.c_rec = _curve(self.p_overlay, "#555555", "recorded")
        self.c_base = _curve(self.p_overlay, "#1f77b4", "baseline")
        self.c_aug = _curve(self.p_overlay, "#d62728", "augmented (named physics added)")
        self.p_resid = self.plots.addPlot(row=1, col=0, title="held-out residual: recorded − model")
        self.p_resid.addLegend(offset=(5, 5))
        self.p_resid.setLabel("left", "residual", units="m")
        time_axis(self.p_resid, "time in the held-out part")
        self.p_resid.showGrid(x=True, y=True, alpha=0.2)
        self.p_resid.setXLink(self.p_overlay)
        self.r_base = _curve(self.p_resid, "#1f77b4", "baseline")
        self.r_aug = _curve(self.p_resid, "#d62728", "augmented")
        split.addWidget(self.plots)
        split.setSizes([520, 700])
        lay.addWidget(split, 1)

    def set_running(self, source: str, baseline: str) -> None:
        self.header.setText(f"<b>{source}</b>: diagnosing against the {baseline} baseline…")
        self.banner.set_verdict(None)
        self.progress.setValue(0)
        self.step_label.setText("starting")
        self.start_button.setEnabled(False)
        self.cancel_button.setEnabled(True)
        self.named.setRowCount(0)
        self.stages.setRowCount(0)
        self.details.setPlainText("")
        for c in (self.c_rec, self.c_base, self.c_aug, self.r_base, self.r_aug):
            c.setData([], [])

    def show_progress(self, progress) -> None:
        self.progress.setValue(int(1000 * progress.fraction))
        self.step_label.setText(progress.text())

    def set_stopped(self, message: str, can_start: bool) -> None:
        self.step_label.setText(message)
        self.cancel_button.setEnabled(False)
        self.start_button.setEnabled(can_start)

    def show_view(self, view) -> None:
        self.header.setText(f"<b>{view.source}</b>: baseline {view.baseline_kind}; {view.origin}; "
                            f"{view.seconds:.0f} s")
        self.banner.set_verdict((view.level(), view.sentence()))
        self.progress.setValue(1000)
        self.named.setRowCount(len(view.named))
        for i, (cid, explanation, params, before, after) in enumerate(view.named):
            size = ", ".join(f"{k} = {v:.4g}{(' ' + u) if u else ''}" for k, v, u in params)
            cells = [cid, size, f"{nrmse_text(before)} → {nrmse_text(after)}", explanation]
            for j, text in enumerate(cells):
                self.named.setItem(i, j, QtWidgets.QTableWidgetItem(text))
        self.stages.setRowCount(len(view.stages))
        for i, (stage, before, after) in enumerate(view.stages):
            for j, text in enumerate((stage, nrmse_text(before), nrmse_text(after))):
                item = QtWidgets.QTableWidgetItem(text)
                if j:
                    item.setTextAlignment(QtCore.Qt.AlignRight | QtCore.Qt.AlignVCenter)
                self.stages.setItem(i, j, item)
        lines = [view.result]
        if view.baseline_note:
            lines.append(f"warning: {view.baseline_note}")
        if view.unexplained:
            lines.append(f"unexplained: {view.unexplained}")
        if not view.named and view.detection_limits:
            lines.append("not seen above (detection limits on this record): "
                         + ", ".join(f"{cid} {p} {v:.3g}" for cid, p, v in view.detection_limits))
        if view.named:
            lines.append("augmented model:\n" + view.equation)
        self.details.setPlainText("\n".join(lines))
        t, rec, base, aug = overlay_arrays(view)
        for c, y in ((self.c_rec, rec), (self.c_base, base), (self.c_aug, aug), (self.r_base, rec - base),
                     (self.r_aug, rec - aug)):
            set_series(c, t, y)
        if view.overlay is not None:
            self.p_overlay.setTitle(f"held-out samples of stage '{view.overlay[0]}': held-out NRMSE "
                                    f"{nrmse_text(view.held_before)} → {nrmse_text(view.held_after)}")


def set_series(curve, x, y) -> None:
    """setData that accepts empty arrays."""
    x = np.asarray(x)
    if x.size == 0:
        curve.setData([], [])
    else:
        curve.setData(x, np.asarray(y))
