"""`shakerlab sim serve`: prints every instrument's address; the addresses answer."""
import re
import subprocess
import sys

from drivers.laser_sensor import LaserSensor
from drivers.power_amplifier import PowerAmplifier
from drivers.signal_generator import SignalGenerator
from shakerlab.cli import main

SERVE = [sys.executable, "-c", "import sys; from shakerlab.cli import main; sys.exit(main(sys.argv[1:]))"]


def test_serve_prints_addresses_that_answer():
    proc = subprocess.Popen(SERVE + ["sim", "serve", "--pty", "--speed", "max", "--duration", "20"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines = [proc.stdout.readline().strip() for _ in range(4)]
        found = {}
        for line in lines:
            m = re.fullmatch(r"(\S+)\s+(127\.0\.0\.1):(\d+)(?:\s+pty (/\S+))?", line)
            assert m, line
            found[m.group(1)] = (f"{m.group(2)}:{m.group(3)}", m.group(4))
        assert set(found) == {"generator", "amplifier", "sensor_base", "sensor_tip"}
        assert found["amplifier"][1] is None and found["generator"][1].startswith("/dev/")
        with SignalGenerator("socket://" + found["generator"][0]) as g:
            assert "SIM33521B" in g.identify()
        with SignalGenerator(found["generator"][1]) as g:  # and over its pty
            assert "SIM33521B" in g.identify()
        with PowerAmplifier(found["amplifier"][0]) as a:
            assert a.identify().startswith("shakerlab")
        for name in ("sensor_base", "sensor_tip"):
            with LaserSensor("socket://" + found[name][0]) as s:
                assert s.identify().endswith(name.split("_")[1])
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_serve_rejects_bad_options(capsys):
    assert main(["sim", "serve", "--speed", "-1"]) == 2
    assert "--speed" in capsys.readouterr().err
    assert main(["sim", "serve", "--sim-speed", "fast"]) == 2
    assert "--speed must be a positive number, 0 or 'max'" in capsys.readouterr().err
    assert main(["sim", "serve", "--generator-port", "70000"]) == 2
    assert "--generator-port" in capsys.readouterr().err
    assert main(["sim", "serve", "--config", "/nonexistent/sim.toml", "--duration", "0"]) == 2
    assert "/nonexistent/sim.toml" in capsys.readouterr().err
