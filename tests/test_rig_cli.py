"""`shakerlab acquire` as a user runs it: in-process on the simulated rig, and as a separate
process against a simulated rig served by the test (SIGKILL -> the amplifier watchdog mutes;
Ctrl-C -> ramp down, clean file)."""
import os
import signal
import subprocess
import sys
import time

import pytest

from rig.config import DEFAULT_RIG_PATH
from shakerlab.cli import main
from shakerlab.runfile.reader import read_events, read_info, read_run
from sim_backend.rig import SimulatedRig

from test_rig_acquisition import SMALL_PROTOCOL


def test_acquire_on_the_embedded_simulated_rig(tmp_path, capsys):
    proto = tmp_path / "p.toml"
    proto.write_text(SMALL_PROTOCOL)
    out = tmp_path / "run.h5"
    assert main(["acquire", "--sim-speed", "0", "--protocol", str(proto), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "starting the simulated rig" in text
    assert "stage nonlinear begins" in text
    assert "run complete" in text and "samples lost: 0" in text
    assert "resonance" in text and "final level" in text
    info = read_info(out)
    assert info["status"] == "complete" and list(info["stages"])[-1] == "validation"
    # refuses to overwrite
    assert main(["acquire", "--sim-speed", "0", "--protocol", str(proto), "-o", str(out)]) == 2
    assert "file exists" in capsys.readouterr().err


WATCHDOG_S = 2.0


def _config_for(sim, tmp_path, watchdog=WATCHDOG_S):
    a = sim.addresses
    text = DEFAULT_RIG_PATH.read_text()
    for old, new in (('"socket://127.0.0.1:5025"', f'"{a["generator"]}"'), ('"127.0.0.1:5020"', f'"{a["amplifier"]}"'),
                     ('"socket://127.0.0.1:5030"', f'"{a["sensor_base"]}"'),
                     ('"socket://127.0.0.1:5031"', f'"{a["sensor_tip"]}"'),
                     ("watchdog_timeout_s = 2.0", f"watchdog_timeout_s = {watchdog}")):
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "rig.toml"
    path.write_text(text)
    return path


def _start(tmp_path, sim):
    proto = tmp_path / "p.toml"
    proto.write_text(SMALL_PROTOCOL)
    cfg = _config_for(sim, tmp_path)
    out = tmp_path / "run.h5"
    proc = subprocess.Popen(
        [sys.executable, "-m", "shakerlab.cli", "acquire", "--config", str(cfg), "--protocol", str(proto),
         "-o", str(out)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        lines.append(line)
        if "stage linear begins" in line or not line:
            break
    assert "stage linear begins" in lines[-1], "".join(lines)
    time.sleep(1.0)  # mid-stage: ramped up, acquiring, flushed
    return proc, out


@pytest.fixture
def realtime_sim():
    with SimulatedRig(speed=1.0, seed=5) as sim:
        yield sim


def test_sigkill_mid_stage_watchdog_mutes_and_file_opens(tmp_path, realtime_sim):
    sim = realtime_sim
    proc, out = _start(tmp_path, sim)
    try:
        assert sim.world.is_driven()  # the shaker runs when the controller dies
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        t_kill = time.monotonic()
        proc.wait()
    while sim.world.is_driven() and time.monotonic() - t_kill < 3.0:
        time.sleep(0.01)
    muted_after = time.monotonic() - t_kill
    assert not sim.world.is_driven()
    assert muted_after < WATCHDOG_S + 0.3  # within the watchdog timeout (+ polling)
    from drivers.power_amplifier import PowerAmplifier

    with PowerAmplifier(sim.addresses["amplifier"]) as amp:
        assert amp.faults.watchdog  # it was the watchdog that muted the output
    assert not out.exists()  # recorded as run.h5.partial until closed: the crash left it there
    run = read_run(out.with_name("run.h5.partial"))  # opens directly
    assert run.attrs["clean_close"] is False and run.attrs["status"] == "running"
    lin = run.stage("linear")
    assert lin.t.size >= 0.4 * 10000  # the data up to the last flush (>= 0.4 s of the 1 s since begin)
    assert lin.settings["status"] == "recording"


def test_ctrl_c_ramps_down_and_closes_the_file(tmp_path, realtime_sim):
    sim = realtime_sim
    proc, out = _start(tmp_path, sim)
    proc.send_signal(signal.SIGINT)
    rest, _ = proc.communicate(timeout=30)
    assert proc.returncode == 130, rest
    assert "Ctrl-C" in rest and "run aborted" in rest
    assert not sim.world.is_driven()
    info = read_info(out)
    assert info["clean_close"] and info["status"] == "aborted"
    assert any("Ctrl-C" in e["message"] and e["level"] == "warning" for e in read_events(out))


def test_unreachable_instrument_is_a_clear_error(tmp_path, capsys):
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = tmp_path / "rig.toml"
    cfg.write_text(DEFAULT_RIG_PATH.read_text().replace("socket://127.0.0.1:5025", f"socket://127.0.0.1:{port}"))
    assert main(["acquire", "--config", str(cfg), "-o", str(tmp_path / "r.h5")]) == 2
    err = capsys.readouterr().err
    assert "cannot reach the instruments" in err and "signal generator" in err
    assert not (tmp_path / "r.h5").exists()
