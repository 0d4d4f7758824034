"""The operator window (pytest-qt, offscreen) on the real simulated rig: real sockets, a real pymodbus
amplifier, real HDF5 files. Runs are in real time (the window's default) and short; each test aborts
or opens a recorded file."""
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


@pytest.fixture
def window(qtbot, tmp_path):
    w = MainWindow(output_dir=tmp_path / "runs", speed=1.0, seed=2, auto_reconstruct=False)
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
    with simulated_rig(speed=None, seed=5) as (sim, cfg):
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
    proc = subprocess.Popen([sys.executable, "-m", "shakerlab.cli", "gui", "--start", "--output-dir", str(out)],
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
