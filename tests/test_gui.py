"""The operator window (pytest-qt, offscreen) on the real simulated rig: real sockets, a real pymodbus
amplifier, real HDF5 files. Runs are short, at 3 x real time (SPEED) or in real time (the window's
default); each test aborts or opens a recorded file."""
import h5py
import numpy as np
import pytest
from PySide6 import QtCore

from drivers.power_amplifier import PowerAmplifier
from rig.gui.window import MainWindow
from shakerlab.runfile.results import add_result, read_results
from shakerlab.runfile.reader import read_events, read_info

PROTOCOL = """
[run]
settle_s = 0.2
[linear]
frequency_hz = 8.0
amplitude_vpp = 0.4
duration_s = 1.0
[resonance_search]
start_hz = 8.0
stop_hz = 25.0
steps = 5
refine_steps = 2
amplitude_vpp = 0.05
settle_s = 0.6
measure_s = 0.3
[nonlinear]
start_vpp = 0.1
step_factor = 1.8
max_vpp = 1.0
dwell_s = 0.6
analysis_s = 0.3
hold_s = 0.4
[[validation]]
frequency_factor = 0.8
amplitude_fraction = 0.8
duration_s = 1.0
"""

# the window's simulated rig runs at 3 x real time (its speed spin box; up to 20): a third of the wall
# time waiting for a run to reach a stage. The live-amplitude test sets 1 x (real time) itself (see there)
SPEED = 3.0


@pytest.fixture
def window(qtbot, tmp_path):
    w = MainWindow(output_dir=tmp_path / "runs", speed=SPEED, seed=2, auto_reconstruct=False)
    qtbot.addWidget(w)
    w.resize(1200, 800)
    w.show()
    w.set_protocol_text(PROTOCOL, "test protocol")
    yield w
    w.shutdown()


def _amplifier_enabled(sim) -> bool:
    with PowerAmplifier(sim.addresses["amplifier"]) as amp:
        return amp.enabled


def _start(qtbot, w):
    qtbot.mouseClick(w.protocol_panel.start_button, QtCore.Qt.LeftButton)
    assert w.running(), w.last_error


def test_live_plots_grow_and_abort_ramps_down_mutes_and_closes_the_file(qtbot, window):
    w = window
    # real time, the window's default: the live amplitude (half peak-to-peak of the recorded motion,
    # ramp ringing included) is compared below with the stage's fundamental within a margin set on
    # runs at this speed (the window's sampling at 3 x is checked in tests/test_gui_live_state.py)
    w.connection.speed.setValue(1.0)
    _start(qtbot, w)
    assert not w.protocol_panel.start_button.isEnabled() and w.protocol_panel.abort_button.isEnabled()
    # the linear stage ends after ~1.9 s of rig time: the linear step is known, the loop is drawn
    qtbot.waitUntil(lambda: w.live.linear is not None, timeout=15000)
    assert w.live.linear.K_m == pytest.approx(8000.0, rel=0.03)  # simulator: k_m + alpha_m = 8000 1/s^2
    # drawn from windows starting 0.5 s after a setpoint: here at each frequency of the resonance search
    qtbot.waitUntil(lambda: w.plots.c_loop.xData is not None and w.plots.c_loop.xData.size > 0, timeout=10000)
    assert w.connection.light_connected.state == "ok"
    assert "SIM" in w.connection.identity["amplifier"].text().upper()
    x1 = w.plots.c_rel.xData
    assert x1 is not None and x1.size > 1000
    # still growing: redrawn from the ring buffer as samples arrive
    qtbot.waitUntil(lambda: w.plots.c_rel.xData[-1] > x1[-1] + 0.2, timeout=5000)
    assert np.all(np.isfinite(w.plots.c_rel.yData))
    frames = w.frames
    amps = w.plots.c_amp["linear"].yData
    assert amps.size >= 5

    qtbot.mouseClick(w.protocol_panel.abort_button, QtCore.Qt.LeftButton)
    assert w.protocol_panel.abort_button.text() == "CUT OUTPUT NOW"
    assert w.protocol_panel.abort_button.isEnabled()
    qtbot.waitUntil(lambda: w.last_outcome is not None, timeout=10000)
    out = w.last_outcome
    assert out.status == "aborted" and "ABORT" in out.reason
    assert w.frames > frames  # the window kept redrawing
    assert not w.sim.world.is_driven()
    assert _amplifier_enabled(w.sim) is False
    with h5py.File(out.path, "r") as f:  # closed by the recorder: opens read-only, marked clean
        assert bool(f.attrs["clean_close"]) is True
        assert f["entry"].attrs["status"] == "aborted"
    messages = [e["message"] for e in read_events(out.path)]
    assert any("ramping" in m and "to zero" in m for m in messages)
    assert not any("cut at once" in m for m in messages)
    # the live amplitude of the linear stage matches the recorded stage's own analysis (fundamental)
    # compared over the whole stage (read after the run, not the mid-run snapshot above, whose
    # span depends on machine load and may hold only the start-up ringing)
    resp = read_info(out.path)["stages"]["linear"]["summary"]["response"]
    stage_amps = w.live.amplitude_series()["linear"][1]
    assert stage_amps.size >= amps.size
    assert np.median(stage_amps) == pytest.approx(resp["relative_amplitude"], rel=0.2)  # the level dominates
    assert w.protocol_panel.start_button.isEnabled() and w.protocol_panel.abort_button.text() == "ABORT"


def test_pause_resume_then_second_abort_cuts_at_once(qtbot, window):
    w = window
    _start(qtbot, w)
    qtbot.waitUntil(lambda: w.live.drive.output and w.live.drive.amplitude_vpp >= 0.3, timeout=15000)
    pause = w.protocol_panel.pause_button
    qtbot.mouseClick(pause, QtCore.Qt.LeftButton)
    assert pause.text() == "Resume"
    qtbot.waitUntil(lambda: w.live.state == "paused", timeout=5000)
    assert not w.sim.world.is_driven()  # paused = output ramped to zero
    qtbot.waitUntil(lambda: "paused" in w.protocol_panel.stage_label.text(), timeout=2000)
    qtbot.mouseClick(pause, QtCore.Qt.LeftButton)
    qtbot.waitUntil(lambda: w.live.state == "running" and w.live.drive.amplitude_vpp >= 0.3, timeout=5000)
    qtbot.mouseClick(w.protocol_panel.abort_button, QtCore.Qt.LeftButton)
    qtbot.mouseClick(w.protocol_panel.abort_button, QtCore.Qt.LeftButton)
    qtbot.waitUntil(lambda: w.last_outcome is not None, timeout=10000)
    assert w.last_outcome.status == "aborted"
    assert not w.sim.world.is_driven()
    assert any("cut at once" in e["message"] for e in read_events(w.last_outcome.path))


def test_closing_the_window_mid_run_aborts_safely(qtbot, window):
    w = window
    _start(qtbot, w)
    qtbot.waitUntil(lambda: w.live.drive.output and w.live.drive.amplitude_vpp > 0.1, timeout=15000)
    sim, path = w.sim, w.run_path
    w.close()
    assert w.isVisible()  # stays open while the output ramps down
    qtbot.waitUntil(lambda: not w.isVisible(), timeout=10000)
    assert not w.running()
    assert not sim.world.is_driven()
    assert w.sim is None  # the simulated rig was stopped with the window
    info = read_info(path)
    assert info["clean_close"] and info["status"] == "aborted"
    assert info["stages"]["linear"]["n_samples"] > 1000
    assert any("window closed" in e["message"] for e in read_events(path))


def test_amplifier_fault_lights_up_and_trips_the_run(qtbot, window, tmp_path):
    import re

    from rig.config import DEFAULT_RIG_PATH

    w = window
    cfg = tmp_path / "low-current.toml"  # the amplifier's own over-current trip below the linear stage's current
    cfg.write_text(re.sub(r"^current_limit_a = .*$", "current_limit_a = 0.02", DEFAULT_RIG_PATH.read_text(), flags=re.M))
    w.connection.config_path.setText(str(cfg))
    _start(qtbot, w)
    qtbot.waitUntil(lambda: w.last_outcome is not None, timeout=15000)
    assert w.last_outcome.status == "tripped" and "over_current" in w.last_outcome.reason
    assert w.connection.light_fault.state == "bad" and "over_current" in w.connection.light_fault.toolTip()
    assert w.connection.light_watchdog.state == "off" and w.connection.light_output.state == "off"
    assert not w.sim.world.is_driven()
    assert read_info(w.last_outcome.path)["clean_close"]


def test_connect_identifies_the_instruments(qtbot, window):
    w = window
    qtbot.mouseClick(w.connection.connect_button, QtCore.Qt.LeftButton)
    qtbot.waitUntil(lambda: w.connection.light_connected.state == "ok", timeout=10000)
    assert "SIM33521B" in w.connection.identity["generator"].text()
    assert w.connection.address["amplifier"].text() == w.sim.addresses["amplifier"]
    assert not w.running()


def test_bad_protocol_or_limit_is_refused_before_anything_moves(qtbot, window):
    w = window
    w.set_protocol_text(PROTOCOL.replace("amplitude_vpp = 0.4", "amplitude_vpp = -0.4"), "bad protocol")
    assert w.start_run() is False
    assert "[linear] amplitude_vpp" in w.last_error and "bad protocol" in w.last_error
    w.set_protocol_text(PROTOCOL.replace("max_vpp = 1.0", "max_vpp = 9.0"), "too strong")
    assert w.start_run() is False
    assert "max_generator_vpp" in w.last_error
    w.set_protocol_text(PROTOCOL.replace("[linear]", "[linear"), "broken toml")
    assert w.start_run() is False
    assert "not valid TOML" in w.last_error
    assert not w.running() and w.sim is None
    assert not (w.output_dir.exists() and any(w.output_dir.iterdir()))


@pytest.fixture(scope="module")
def recorded_run(tmp_path_factory):
    """A run recorded on the simulated rig (lockstep) with the simulator's true model stored as its result."""
    import tomllib

    from recon.model import HystereticModel
    from rig.protocol import parse_protocol
    from rig.session import acquire, simulated_rig

    path = tmp_path_factory.mktemp("gui") / "run.h5"
    # 1.5 s at rest before each stage: with 0.2 s the specimen still rings from the nonlinear stage when the
    # validation stage starts, and a model simulated from rest cannot match it (NRMSE 0.44 vs 0.04)
    # and a nonlinear stage long enough for the sparse regression to find the hysteresis
    text = (PROTOCOL.replace("settle_s = 0.2", "settle_s = 1.5").replace("step_factor = 1.8", "step_factor = 1.5")
            .replace("dwell_s = 0.6", "dwell_s = 0.8").replace("hold_s = 0.4", "hold_s = 2.0"))
    # sampled at 1 kHz (test_closed_loop.rig_toml_1khz), a tenth of the samples to stream and write: the true
    # model on the validation stage measured NRMSE 0.0362 at 1 kHz and 0.0363 at 10 kHz, the loops' spans
    # within 1 % of the simulated loop at either rate
    from test_closed_loop import rig_toml_1khz

    rig = rig_toml_1khz(path.parent)
    with simulated_rig(speed=None, seed=5, rig_config=rig) as (sim, cfg):
        out = acquire(cfg, parse_protocol(tomllib.loads(text), text, "test"), path, lockstep=True)
        truth = sim.world.truth()
    assert out.status == "complete", out.reason
    model = HystereticModel(excitation="base", **truth)
    return path, model, truth


def test_open_recorded_run_fills_the_result_panels(qtbot, window, recorded_run):
    w = window
    path, model, truth = recorded_run
    d = model.to_dict()
    add_result(path, "reconstruction", {**d, "validation": {"stage": "validation"}, "truth": truth},
               text=str(model))
    add_result(path, "diagnosis", {"text": "hysteresis present (test entry)"})
    assert w.open_run(path)
    qtbot.waitUntil(lambda: w.last_view is not None, timeout=15000)
    r = w.results
    eq = r.equation.toPlainText()
    assert eq.startswith("y'' + 3.5 y' + 6000 y") and "z' = 2000 y' - 300 |y'| z - 200 y' |z|" in eq
    assert all(term.replace("dy", "y'") in eq for term in truth["fn_m"])
    assert r.table.rowCount() == 5 + len(truth["fn_m"])
    names = [r.table.item(i, 0).text() for i in range(r.table.rowCount())]
    assert names[:5] == ["c_m", "k_m", "alpha_m", "gamma", "delta"]
    assert float(r.table.item(1, 1).text()) == pytest.approx(truth["k_m"], rel=1e-5)
    assert not r.table.isColumnHidden(3)  # the stored result carries the simulator's truth
    assert r.c_meas.yData.size > 1000 and r.c_sim.yData.size == r.c_meas.yData.size
    assert r.c_zsim.xData.size > 100
    # the loop implied by the data and the (true) model's other terms lies on the simulated loop
    assert np.ptp(r.c_zmeas.yData) == pytest.approx(np.ptp(r.c_zsim.yData), rel=0.1)
    assert np.ptp(r.c_zmeas.xData) == pytest.approx(np.ptp(r.c_zsim.xData), rel=0.05)
    # the true model, simulated on the recorded validation stage, matches the measurement
    assert w.last_view.nrmse < 0.1
    assert "NRMSE" in r.header.text() and "stored result" in r.header.text()
    assert w.tabs.currentWidget() is r
    assert r.diagnosis_box.isVisibleTo(w) and "hysteresis present" in r.diagnosis.toPlainText()


def test_opening_a_missing_file_names_it(qtbot, window, tmp_path):
    w = window
    assert w.open_run(tmp_path / "nope.h5")
    qtbot.waitUntil(lambda: bool(w.last_error), timeout=5000)
    assert "nope.h5" in w.last_error and "no such file" in w.last_error
    assert w.results.equation.toPlainText() == ""


# the short protocol the rig tests run (test_rig_cli imports it the same way)
from test_rig_acquisition import SMALL_PROTOCOL as RECON_PROTOCOL  # noqa: E402


@pytest.mark.slow
def test_reconstruct_off_the_gui_thread_and_write_back(qtbot, window, tmp_path):
    """A run without results: the window reconstructs it in a worker thread and writes the result back."""
    import tomllib

    from rig.protocol import parse_protocol
    from rig.session import acquire, simulated_rig

    w = window
    path = tmp_path / "run.h5"
    with simulated_rig(speed=None, seed=3) as (sim, cfg):
        out = acquire(cfg, parse_protocol(tomllib.loads(RECON_PROTOCOL), RECON_PROTOCOL, "t"), path, lockstep=True)
        truth = sim.world.truth()
    assert out.status == "complete", out.reason
    assert w.open_run(path)
    frames = w.frames
    qtbot.waitUntil(lambda: w.last_view is not None or bool(w.last_error), timeout=120000)
    assert not w.last_error
    assert w.frames > frames + 10  # the GUI kept redrawing while recon ran in its thread
    r = w.results
    assert "y''" in r.equation.toPlainText() and r.table.rowCount() >= 5
    assert "reconstructed now" in r.header.text()
    assert list(read_results(path)) == ["reconstruction_000"]
    k = float(r.table.item(1, 1).text()) + float(r.table.item(2, 1).text())  # k_m + alpha_m
    assert k == pytest.approx(truth["k_m"] + truth["alpha_m"], rel=0.1)
    assert r.c_zmeas.xData.size > 100  # the loop implied by the data is drawn too
    assert not r.diagnosis_box.isVisibleTo(w)  # no diagnosis in the file: no panel


def test_shakerlab_gui_command_opens_and_quits(qapp, tmp_path):
    """`shakerlab gui` (the handler behind the sub-command) runs the event loop and returns on quit."""
    from PySide6 import QtWidgets

    from rig.gui import run_gui
    from shakerlab.cli import build_parser, main

    args = build_parser().parse_args(["gui", "--sim-speed", "0", "--output-dir", str(tmp_path / "runs")])
    assert args.handler is run_gui and args.sim_speed == 0.0 and args.config is None
    seen = {}

    def look_and_quit():
        wins = [w for w in QtWidgets.QApplication.topLevelWidgets() if w.isVisible() and w.windowTitle()
                .startswith("shakerlab")]
        seen["windows"] = wins
        seen["speed"] = wins[0].connection.speed.value() if wins else None
        seen["simulated"] = wins[0].connection.simulated.isChecked() if wins else None
        for w in wins:
            w.close()  # closing the last window ends the event loop, as for the operator

    QtCore.QTimer.singleShot(300, look_and_quit)
    assert main(["gui", "--sim-speed", "0", "--output-dir", str(tmp_path / "runs")]) == 0
    assert len(seen["windows"]) == 1 and seen["speed"] == 0.0 and seen["simulated"] is True
    assert not (tmp_path / "runs").exists()  # nothing ran


def test_plots_slow_down_while_the_acquisition_is_behind(qtbot, window, monkeypatch):
    w = window
    w.connection.speed.setValue(1.0)   # real time: the waits below count the window's ticks, not the rig's time
    _start(qtbot, w)
    qtbot.waitUntil(lambda: w.live.blocks > 5, timeout=15000)
    monkeypatch.setattr(w.live, "lag", lambda speed: 1.0)   # as if the acquisition thread were starved
    qtbot.waitUntil(lambda: w.throttled, timeout=2000)
    t0, f0 = w.ticks, w.frames
    qtbot.waitUntil(lambda: w.ticks >= t0 + 20, timeout=5000)
    assert w.frames - f0 <= 5                                  # 1 redraw in 5 ticks
    assert "behind real time" in w.log_view.toPlainText()
    monkeypatch.setattr(w.live, "lag", lambda speed: 0.0)
    qtbot.waitUntil(lambda: not w.throttled, timeout=2000)
    t0, f0 = w.ticks, w.frames
    qtbot.waitUntil(lambda: w.ticks >= t0 + 10, timeout=5000)
    assert w.frames - f0 >= 9
    w.abort()
    qtbot.waitUntil(lambda: w.last_outcome is not None, timeout=10000)


def test_sigterm_to_shakerlab_gui_mid_run_aborts_safely(tmp_path):
    """`shakerlab gui --start` in its own process; SIGTERM mid-run ramps down, mutes, closes the file, exits."""
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "runs"
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    proc = subprocess.Popen([sys.executable, "-m", "shakerlab.cli", "gui", "--start", "--output-dir", str(out),
                             "--sim-speed", str(SPEED)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 60
        path = None
        while time.monotonic() < deadline:  # samples are being recorded (the writer holds the HDF5 lock,
            # the run is recorded in RUN.h5.partial and renamed to RUN.h5 when it is closed
            files = [f for f in out.glob("run-*.h5*") if f.suffix in (".h5", ".partial")] if out.exists() else []
            if files:
                path = files[0]
                if path.stat().st_size > 150_000:
                    break
            time.sleep(0.1)
        assert path is not None, proc.stdout.read() if proc.poll() is not None else "no run file"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    path = path.with_name(path.name.removesuffix(".partial"))
    assert path.exists() and not path.with_name(path.name + ".partial").exists()
    info = read_info(path)
    assert info["clean_close"] and info["status"] == "aborted"
    assert info["stages"]["linear"]["n_samples"] > 1000
    assert any("window closed" in e["message"] for e in read_events(path))
    assert any("ramping" in e["message"] and "to zero" in e["message"] for e in read_events(path))


# -- what the operator sees: verdict banner, the run tab at rest, units, the equation, diagnose ---------------

OPEN_LOOP = PROTOCOL
CLOSED_LOOP = PROTOCOL.replace("amplitude_vpp = 0.4\nduration_s = 1.0", "base_amplitude_mm = 0.05\nduration_s = 1.0")


def test_idle_run_tab_counts_no_stages_and_shows_sine_control_only_for_a_closed_loop_protocol(qtbot, window):
    w = window
    qtbot.wait(50)
    assert w.protocol_panel.progress.text() == "no run yet"          # not "0 / 1 stages" before any run
    plots = w.plots
    assert not plots.control_visible()                               # open loop: no empty sine-control row
    h_open = plots.p_traces.geometry().height()
    w.set_protocol_text(CLOSED_LOOP, "closed loop")
    qtbot.waitUntil(lambda: plots.p_traces.geometry().height() < 0.9 * h_open, timeout=2000)
    assert plots.control_visible()
    w.set_protocol_text(OPEN_LOOP, "open loop")
    qtbot.waitUntil(lambda: plots.p_traces.geometry().height() > 0.95 * h_open, timeout=2000)
    assert not plots.control_visible()
    # every time axis reads seconds, also over a span pyqtgraph would have shown in ms
    for p in (plots.p_traces, plots.p_rel, plots.p_amp, plots.p_ctrl, w.results.p_overlay, w.diagnosis.p_overlay):
        p.setXRange(0.0, 0.004, padding=0)
        ax = p.getAxis("bottom")
        assert ax.labelUnits == "s" and ax.autoSIPrefixScale == 1.0 and "(s)" in ax.labelString()


def test_equation_wraps_only_between_terms():
    from rig.gui.panels import wrap_terms

    eq = "y'' + 3.5 y' + 6000 y + 2e+05 y^2 + z = -x_base''\nz' = 2000 y' - 300 |y'| z - 200 y' |z|"
    assert wrap_terms(eq, 200) == eq
    text = wrap_terms(eq, 22)
    assert text.split("\n") == ["y'' + 3.5 y' + 6000 y", "    + 2e+05 y^2 + z", "    = -x_base''",
                                 "z' = 2000 y'", "    - 300 |y'| z", "    - 200 y' |z|"]
    assert " ".join(text.split()) == " ".join(eq.split())


def test_fn_units():
    from rig.gui.results import fn_unit

    assert fn_unit("y^2") == "1/(m s^2)"
    assert fn_unit("y^3") == "1/(m^2 s^2)"
    assert fn_unit("dy^2") == "1/m"
    assert fn_unit("y^2*dy") == "1/(m^2 s)"
    assert fn_unit("y") == "1/s^2"
    assert fn_unit("y^3", component=True) == "N/m^3"
    assert fn_unit("dy^2", component=True) == "N s^2/m^2"
    assert fn_unit("not a term") == ""


@pytest.mark.parametrize("adequacy, level, words", [
    ({"verdict": "adequate", "admissible": True, "validation_nrmse": 0.0047, "nrmse_limit": 0.01, "reasons": []},
     "green", ["adequate", "0.470 %", "1.00 %"]),
    ({"verdict": "adequate", "admissible": True, "validation_nrmse": 0.006, "nrmse_limit": 0.01, "reasons": [],
      "fallback": {"used": True, "kind": "bouc_wen", "trigger": "inadequate"}},
     "amber", ["fallback", "bouc_wen", "predicted the held-out data worse", "adequate"]),
    ({"verdict": "inadequate", "admissible": True, "validation_nrmse": 0.2, "nrmse_limit": 0.01,
      "reasons": ["validation NRMSE 0.2 is above 0.01"], "fallback": {"used": True, "kind": "linear",
                                                                       "trigger": "inadmissible"}},
     "red", ["fallback", "not physically admissible", "linear", "inadequate", "diagnose"]),
    ({"verdict": "inadequate", "admissible": False, "validation_nrmse": 0.02, "nrmse_limit": 0.01,
      "reasons": ["the model is not physically admissible"]}, "red", ["inadequate", "not physically admissible"]),
    (None, "grey", ["no verdict"]),
])
def test_verdict_sentence(adequacy, level, words):
    from rig.gui.results import verdict_line

    got_level, sentence = verdict_line(adequacy)
    assert got_level == level
    assert all(w in sentence.lower() for w in words), sentence


def test_result_view_shows_the_verdict_banner_units_and_an_unbroken_equation(qtbot, window, recorded_run, tmp_path):
    import shutil

    from rig.gui.panels import BANNER_STYLES

    w = window
    src, model, truth = recorded_run
    path = tmp_path / "run.h5"
    shutil.copy(src, path)
    good = {"verdict": "adequate", "admissible": True, "validation_nrmse": 0.004, "noise_floor_nrmse": 0.001,
            "nrmse_limit": 0.01, "fn_terms": 3, "reasons": []}
    add_result(path, "reconstruction", {**model.to_dict(), "validation": {"stage": "validation"}, "adequacy": good},
               text=str(model))
    w.resize(700, 800)                                     # narrow: the equation has to wrap
    assert w.open_run(path)
    qtbot.waitUntil(lambda: w.last_view is not None, timeout=15000)
    r = w.results
    assert r.banner.isVisibleTo(w) and r.banner.level == "green" and "adequate" in r.banner.text().lower()
    assert BANNER_STYLES["green"][0] in r.banner.styleSheet()
    units = {r.table.item(i, 0).text(): r.table.item(i, 2).text() for i in range(r.table.rowCount())}
    assert units["fn_m[y^2]"] == "1/(m s^2)" and units["k_m"] == "1/s^2"
    assert all(units[n] for n in units)                    # every row has its unit
    # the equation, wrapped to the narrow view, breaks only between terms
    lines = r.equation.toPlainText().split("\n")
    assert len(lines) > 2 and r.equation.lineWrapMode() == r.equation.LineWrapMode.NoWrap
    assert all(line.startswith(("y''", "z'")) or line.lstrip()[:2] in ("+ ", "- ", "= ") for line in lines), lines
    assert " ".join(r.equation.toPlainText().split()) == " ".join(w.last_view.equation.split())
    assert max(len(line) for line in lines) <= r.equation.columns()
    # an inadequate stored result: red, with the way forward
    bad = dict(good, verdict="inadequate", validation_nrmse=0.2, reasons=["validation NRMSE 0.2 is above 0.01"])
    add_result(path, "reconstruction", {**model.to_dict(), "validation": {"stage": "validation"}, "adequacy": bad},
               text=str(model))
    w.last_view = None
    assert w.open_run(path)
    qtbot.waitUntil(lambda: w.last_view is not None, timeout=15000)
    assert r.banner.level == "red" and "inadequate" in r.banner.text().lower() and "diagnose" in r.banner.text().lower()
    assert r.diagnose_button.isEnabled()


def test_a_result_stored_without_a_verdict_is_judged_here(qtbot, window, recorded_run, tmp_path):
    import shutil

    w = window
    src, model, truth = recorded_run
    path = tmp_path / "run.h5"
    shutil.copy(src, path)
    add_result(path, "reconstruction", {**model.to_dict(), "validation": {"stage": "validation"}}, text=str(model))
    assert w.open_run(path)       # the simulator's true model, stored without adequacy
    qtbot.waitUntil(lambda: w.last_view is not None, timeout=15000)
    assert w.last_view.verdict[0] in ("green", "red") and w.results.banner.isVisibleTo(w)
    assert "no verdict" not in w.results.banner.text().lower()


def test_force_run_loop_legend_names_the_force(qtbot, window, tmp_path):
    """A force-excited run: the data-implied loop is inv_m F - ..., never -x_base''."""
    from recon.model import HystereticModel
    from recon.testing.concealed import concealed_run

    run, truth, _, baseline = concealed_run(None, excitation="force", duration=1.0, seed=3)
    path = _run_file(tmp_path / "force.h5", run)
    add_result(path, "reconstruction", {**baseline.to_dict(), "validation": {"stage": "validation"}},
               text=str(baseline))
    w = window
    assert w.open_run(path)
    qtbot.waitUntil(lambda: w.last_view is not None or bool(w.last_error), timeout=20000)
    assert not w.last_error
    labels = [label.text for _, label in w.results.p_loop.legend.items]
    assert any("inv_m F" in t for t in labels), labels
    assert not any("x_base" in t for t in labels), labels
    assert w.results.c_zmeas.xData.size > 100
    assert isinstance(HystereticModel.from_dict(baseline.to_dict()), HystereticModel)


def _run_file(path, run):
    """``run`` (a Run in memory) as a real HDF5 run file, through `shakerlab import` of CSV files."""
    from shakerlab.import_command import import_csv

    files = {}
    for name, st in run.stages.items():
        cols = ["t"] + list(st.channels)
        csv = path.with_name(f"{path.stem}-{name}.csv")
        np.savetxt(csv, np.column_stack([st.t] + [st.channels[c] for c in st.channels]),
                   delimiter=",", header=",".join(cols), comments="")
        files[name] = csv
    return import_csv(path, files)


@pytest.fixture(scope="module")
def friction_run(tmp_path_factory):
    """A short synthetic run with Coulomb friction its baseline model leaves out, as a run file, and
    that baseline as a model JSON."""
    from recon.testing.concealed import concealed_run

    d = tmp_path_factory.mktemp("diag")
    run, truth, extras, baseline = concealed_run("coulomb_friction", duration=1.0, seed=2)
    path = _run_file(d / "friction.h5", run)
    model = d / "baseline.json"
    baseline.save(model)
    add_result(path, "reconstruction", {**baseline.to_dict(), "validation": {"stage": "validation"}},
               text=str(baseline))
    return path, model, extras


def test_diagnose_from_the_window_names_the_friction_with_its_size(qtbot, window, friction_run, tmp_path):
    import shutil

    src, model, extras = friction_run
    path = tmp_path / "run.h5"
    shutil.copy(src, path)
    w = window
    assert w.open_run(path)
    qtbot.waitUntil(lambda: w.last_view is not None, timeout=15000)
    assert w.results.diagnose_button.isEnabled()
    seen = []
    w.signals.diagnosis_progress.connect(lambda p: seen.append((p.fraction, p.step)))
    frames = w.frames
    assert w.diagnose_run(baseline=str(model), candidates=["coulomb_friction", "quadratic_damping"])
    assert w.tabs.currentWidget() is w.diagnosis and w.diagnosis.cancel_button.isEnabled()
    qtbot.waitUntil(lambda: w.diagnosis_state != "running", timeout=120000)
    assert w.diagnosis_state == "done", w.last_error
    assert w.frames > frames + 10                                      # the window kept redrawing
    steps = [s for _, s in seen]
    assert any("fitting candidate coulomb_friction" in s for s in steps), steps
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    v = w.last_diagnosis
    assert v.named and v.named[0][0] == "coulomb_friction"
    size = dict((k, (val, u)) for k, val, u in v.named[0][2])
    assert size["mu"][0] == pytest.approx(extras["mu"], rel=0.15) and size["mu"][1] == "m/s^2"
    assert v.held_after < 0.5 * v.held_before
    d = w.diagnosis
    assert d.banner.isVisibleTo(w) and d.banner.level == "green" and "coulomb_friction" in d.banner.text()
    assert d.named.item(0, 0).text() == "coulomb_friction" and "mu = " in d.named.item(0, 1).text()
    assert "→" in d.named.item(0, 2).text()
    assert d.stages.rowCount() == 3 and d.stages.item(2, 0).text() == "validation"
    assert d.c_rec.yData.size > 100 and d.c_aug.yData.size == d.c_rec.yData.size == d.c_base.yData.size
    # the augmented model follows the held-out record better than the baseline
    rec, base, aug = d.c_rec.yData, d.c_base.yData, d.c_aug.yData
    assert np.sqrt(np.mean((aug - rec) ** 2)) < 0.5 * np.sqrt(np.mean((base - rec) ** 2))
    assert np.std(d.r_aug.yData) < 0.5 * np.std(d.r_base.yData)          # the residuals drawn say the same
    assert not d.cancel_button.isEnabled() and d.start_button.isEnabled()
    assert any(n.startswith("diagnosis_") for n in read_results(path))   # written back into the run file


def test_diagnosis_cancel_stops_the_child_at_once(qtbot, window, friction_run, tmp_path):
    import shutil

    src, model, _ = friction_run
    path = tmp_path / "run.h5"
    shutil.copy(src, path)
    w = window
    assert w.diagnose_run(path, baseline="paper")                       # the slow default: reconstruct first
    qtbot.waitUntil(lambda: w._diag_job.process is not None and w._diag_job.process.is_alive(), timeout=10000)
    process = w._diag_job.process
    qtbot.mouseClick(w.diagnosis.cancel_button, QtCore.Qt.LeftButton)
    qtbot.waitUntil(lambda: w.diagnosis_state == "cancelled", timeout=10000)
    assert not process.is_alive()
    assert "cancelled" in w.diagnosis.step_label.text()
    assert w.diagnosis.start_button.isEnabled() and not w.diagnosis.cancel_button.isEnabled()
    assert not any(n.startswith("diagnosis_") for n in read_results(path))
    assert w.last_diagnosis is None
