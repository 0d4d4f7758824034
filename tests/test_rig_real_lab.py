"""A real lab's instruments: VISA addresses, serial line settings, declared Modbus maps, a manual
amplifier, calibration data and check-rig. Real transports throughout: the simulated generator
through pyvisa-py over TCP, a pty pair, the simulated amplifier's pymodbus server."""
import json
import os
import termios
import tomllib

import pytest
import serial

from drivers.base import SettingRangeError
from drivers.line_link import LineLink, SerialSettings
from drivers.modbus_amplifier import RegisterMap, modbus_amplifier
from drivers.signal_generator import SignalGenerator
from rig.check import check_rig
from rig.config import DEFAULT_RIG_PATH, parse_config
from rig.messages import Acquire, Ramp, SetFrequency
from rig.session import acquire, simulated_rig
from shakerlab.cli import main
from shakerlab.errors import UserFacingError
from shakerlab.runfile.reader import read_events, read_info
from sim_backend import physics as ph
from sim_backend.rig import SimulatedRig


def rig_toml(**tables) -> str:
    """The shipped rig config with tables replaced: {"amplifier": 'kind = "manual"\\ngain = 1.5'}."""
    text = DEFAULT_RIG_PATH.read_text()
    data = tomllib.loads(text)
    out = []
    for name in ("generator", "amplifier"):
        body = tables.get(name)
        if body is None:
            body = "\n".join(f"{k} = {json.dumps(v)}" for k, v in data[name].items())
        out.append(f"[{name}]\n{body}\n")
    for point in ("base", "tip"):
        body = tables.get(point) or "\n".join(f"{k} = {json.dumps(v)}" for k, v in data["sensors"][point].items())
        out.append(f"[sensors.{point}]\n{body}\n")
    for name in ("acquisition", "limits", "check"):
        body = "\n".join(f"{k} = {json.dumps(v)}" for k, v in data.get(name, {}).items())
        out.append(f"[{name}]\n{body}\n{tables.get(name, '')}\n")
    return "\n".join(out)


def config(**tables):
    text = rig_toml(**tables)
    return parse_config(tomllib.loads(text), text, "lab.toml")


# ---- VISA ------------------------------------------------------------------------------------------
def test_the_simulated_generator_through_a_visa_socket_resource():
    with SimulatedRig(speed=None, seed=0) as sim:
        host, port = sim.addresses["generator"].removeprefix("socket://").split(":")
        with SignalGenerator(f"TCPIP::{host}::{port}::SOCKET", visa_library="@py", timeout=2.0) as gen:
            assert gen.identify().startswith("shakerlab,SIM33521B")
            gen.reset()
            gen.frequency = 17.5
            gen.amplitude = 0.25
            assert gen.frequency == 17.5 and gen.amplitude == 0.25
            assert sim.world.G[ph.G_FREQ] == 17.5
            with pytest.raises(SettingRangeError):
                gen.amplitude = 20.0  # refused before sending, never clipped
            gen.set_voltage_limits(-0.5, 0.5)
            gen.amplitude = 0.8
            with pytest.raises(Exception, match="-221"):
                gen.amplitude = 2.0  # the instrument's own refusal, through VISA
            gen.safe_state()
            assert gen.output is False


def test_a_visa_resource_in_the_rig_config():
    cfg = config(generator='resource = "TCPIP0::192.168.1.20::5025::SOCKET"\nvisa_library = "@py"')
    assert cfg.addresses()["generator"] == "TCPIP0::192.168.1.20::5025::SOCKET"
    with pytest.raises(UserFacingError, match=r"\[generator\]: give exactly one of url"):
        config(generator='url = "socket://127.0.0.1:5025"\nresource = "GPIB0::10::INSTR"')
    with pytest.raises(UserFacingError, match=r"\[generator\] url: .* is a VISA resource string"):
        config(generator='url = "USB0::0x0957::0x2C07::MY1234::INSTR"')
    with pytest.raises(UserFacingError, match=r"\[generator\] resource: 'ttyUSB0' is not a VISA resource"):
        config(generator='resource = "ttyUSB0"')


# ---- serial settings ---------------------------------------------------------------------------------
def test_every_serial_setting_reaches_pyserial_on_a_pty():
    master, slave = os.openpty()
    path = os.ttyname(slave)
    try:
        # data bits and parity reach pyserial, which sets them on the terminal when it opens (a Linux
        # pty then keeps 8 data bits and no parity, and refuses them on the next change: no I/O here)
        link = LineLink("vibrometer", path, serial_settings=SerialSettings(data_bits=7, parity="even"))
        assert (link._port.bytesize, link._port.parity) == (serial.SEVENBITS, serial.PARITY_EVEN)
        link.close()
        link = LineLink("vibrometer", path, serial_settings=SerialSettings(data_bits=5, parity="mark"))
        assert (link._port.bytesize, link._port.parity) == (serial.FIVEBITS, serial.PARITY_MARK)
        link.close()
        settings = SerialSettings(baudrate=9600, stop_bits=2, flow_control="rtscts")
        link = LineLink("vibrometer", path, timeout=0.5, write_term="\r\n", read_term="\r",
                        serial_settings=settings)
        port = link._port
        assert (port.baudrate, port.stopbits, port.timeout) == (9600, serial.STOPBITS_TWO, 0.5)
        assert (port.rtscts, port.xonxoff, port.dsrdtr) == (True, False, False)
        # ... and reached the terminal itself
        iflag, oflag, cflag, lflag, ispeed, ospeed, cc = termios.tcgetattr(port.fd)
        assert ispeed == ospeed == termios.B9600
        assert cflag & termios.CSTOPB and cflag & termios.CRTSCTS
        os.write(master, b"VER,1.0\r")
        assert link.query("VER") == "VER,1.0"  # the read termination as set
        assert os.read(master, 64) == b"VER\r\n"  # the write termination as set
        link.close()
        for flow in ("xonxoff", "dsrdtr"):
            link = LineLink("vibrometer", path, serial_settings=SerialSettings(flow_control=flow))
            assert getattr(link._port, flow) and link._port.baudrate == 115200
            link.close()
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("field,value,needle", [
    ("baudrate", "12345", "baudrate: expected one of 300, 600"),
    ("data_bits", "9", "data_bits: expected one of 5, 6, 7, 8"),
    ("parity", '"evn"', "parity: expected one of 'none', 'even'"),
    ("stop_bits", "3", "stop_bits: expected one of 1, 1.5, 2"),
    ("flow_control", '"hardware"', "flow_control: expected one of 'none', 'xonxoff'"),
    ("read_termination", '"\\t"', "read_termination: expected one of"),
    ("timeout_s", "0", "timeout_s: expected a number > 0"),
])
def test_each_serial_setting_is_validated_naming_the_field(field, value, needle):
    base = 'url = "/dev/ttyUSB0"\n' + f"{field} = {value}"
    with pytest.raises(UserFacingError, match=r"lab.toml: \[sensors.base\] " + needle.replace("(", r"\(")):
        config(base=base)
    with pytest.raises(ValueError, match="parity"):
        SerialSettings(parity="evn")


def test_serial_settings_in_the_rig_config_reach_the_drivers():
    cfg = config(base='url = "socket://127.0.0.1:1"\nbaudrate = 9600\nparity = "odd"\nstop_bits = 1.5')
    from rig.instruments import serial_settings
    s = serial_settings(cfg.data["sensors"]["base"])
    assert (s.baudrate, s.parity, s.stop_bits, s.data_bits, s.flow_control) == (9600, "odd", 1.5, 8, "none")


# ---- amplifiers -----------------------------------------------------------------------------------------
SIM_MAP = """kind = "modbus"
address = "127.0.0.1:5020"
gain = 1.0
watchdog_timeout_s = 2.0
[amplifier.registers]
enable = 0
gain = 1
gain_scale = 1000
gain_max = 10
watchdog = 3
heartbeat = 5
current = 17
status = 16
fault_bits = 30
fault_reset = 4
ident = 32"""


def test_a_declared_modbus_map_against_the_pymodbus_server():
    with SimulatedRig(speed=None, seed=0) as sim:
        cfg = config(amplifier=SIM_MAP)
        from rig.instruments import register_map
        amp = modbus_amplifier(sim.addresses["amplifier"], register_map(cfg.data["amplifier"]["registers"]))
        try:
            assert amp.identify() == "shakerlab SIM-PA100 amplifier"
            amp.gain = 2.5
            amp.enabled = True
            amp.watchdog_timeout = 1.5
            A = sim.world.A
            assert A[ph.A_GAIN] == 2.5 and A[ph.A_ENABLE] == 1.0 and sim.amplifier.watchdog_timeout == 1.5
            assert amp.enabled and amp.check_errors() == [] and amp.output_current == 0.0
            with pytest.raises(SettingRangeError):
                amp.gain = 10.5  # beyond gain_max: refused before sending
            assert A[ph.A_GAIN] == 2.5
            amp.heartbeat()
            amp.safe_state()
            assert A[ph.A_ENABLE] == 0.0 and A[ph.A_GAIN] == 0.0
        finally:
            amp.close()
        # a map with only the mute register (front-panel gain): the rest is named as absent
        bare = modbus_amplifier(sim.addresses["amplifier"], RegisterMap(enable=0))
        try:
            with pytest.raises(AttributeError, match="declares no gain register"):
                bare.gain = 1.0
            assert "no identity register" in bare.identify() and bare.output_current is None
        finally:
            bare.close()
        # a whole run through the declared map on the simulated rig
        with simulated_rig(speed=None, seed=1, rig_config=cfg) as (_, run_cfg):
            report = check_rig(run_cfg, lockstep=True)
        assert report.run["status"] == "complete", report.reasons


def test_a_modbus_map_is_validated_naming_the_field():
    with pytest.raises(UserFacingError, match=r"\[amplifier.registers\] enable: missing"):
        config(amplifier='kind = "modbus"\naddress = "10.0.0.5:502"')
    with pytest.raises(UserFacingError, match=r"\[amplifier.registers\] gain_max: missing"):
        config(amplifier='kind = "modbus"\naddress = "10.0.0.5:502"\n[amplifier.registers]\nenable = 3\ngain = 4')
    with pytest.raises(UserFacingError, match=r"\[amplifier.registers\] enable: a register map applies only"):
        config(amplifier='address = "10.0.0.5:502"\n[amplifier.registers]\nenable = 3')
    with pytest.raises(UserFacingError, match=r"\[amplifier.registers\] gain: expected an integer >= 0 and <= 65535"):
        config(amplifier='kind = "modbus"\naddress = "h:502"\n[amplifier.registers]\nenable = 1\ngain = 70000')
    with pytest.raises(UserFacingError, match=r"\[amplifier\] gain: missing; with kind = 'manual'"):
        config(amplifier='kind = "manual"')
    with pytest.raises(UserFacingError, match=r"\[amplifier\] address: a manual amplifier has no remote control"):
        config(amplifier='kind = "manual"\ngain = 1.0\naddress = "h:1"')


class AbortWhenDriven:
    def __init__(self):
        self.runner = None
        self.blocks = []

    def on_block(self, block):
        self.blocks.append(block.amplitude_vpp)
        if block.amplitude_vpp > 0.3 and self.runner is not None:
            self.runner.abort("operator pressed stop")
            self.runner = None


def test_a_manual_amplifier_run_whose_abort_stops_the_generator(tmp_path):
    from rig.protocol import load_protocol

    cfg = config(amplifier='kind = "manual"\ngain = 1.5')
    observer = AbortWhenDriven()

    def plan():
        yield SetFrequency(10.0)
        yield Ramp(0.5, "up")
        yield Acquire(5.0)

    with simulated_rig(speed=None, seed=2, rig_config=cfg) as (sim, run_cfg):
        assert sim.world.A[ph.A_GAIN] == 1.5  # the operator's front panel
        out = acquire(run_cfg, load_protocol(), tmp_path / "manual.h5", lockstep=True, observers=[observer],
                      on_runner=lambda r: setattr(observer, "runner", r), plan=plan())
        assert out.status == "aborted" and out.reason == "operator pressed stop"
        assert sim.world.G[ph.G_OUT] == 0.0 and not sim.world.is_driven()  # the generator was stopped...
        assert sim.world.A[ph.A_ENABLE] == 1.0 and sim.world.A[ph.A_GAIN] == 1.5  # ...the amplifier untouched
    after = observer.blocks[observer.blocks.index(max(observer.blocks)):]
    assert after[-1] == 0.0 and sum(1 for a in after if 0 < a < max(observer.blocks)) >= 5  # ramped, not cut
    info = read_info(out.path)
    amp = info["instruments"]["amplifier"]
    assert amp["settings"]["kind"] == "manual" and amp["settings"]["remote_control"] is False
    assert "manual amplifier" in amp["identity"] and amp["settings"]["gain"] == 1.5
    assert any("manual amplifier: not muted (no remote control), the generator was stopped instead" in e["message"]
               for e in read_events(out.path))


# ---- calibration and check-rig --------------------------------------------------------------------------
def test_calibration_is_data_in_the_run_file(tmp_path):
    from rig.protocol import load_protocol

    cfg = config(base='url = "socket://x:1"\nsensitivity = 1.02\nserial_number = "LK-H052 #4711"\n'
                      'range_m = 0.01\ncalibration_date = "2024-05-02"')

    def plan():
        yield Acquire(0.2)

    with simulated_rig(speed=None, seed=3, rig_config=cfg) as (_, run_cfg):
        out = acquire(run_cfg, load_protocol(), tmp_path / "cal.h5", lockstep=True, plan=plan())
    assert out.status == "complete"
    base = read_info(out.path)["instruments"]["sensor_base"]["settings"]
    assert base["sensitivity"] == 1.02 and base["serial_number"] == "LK-H052 #4711"
    assert base["calibration_date"] == "2024-05-02" and base["measuring_range_m"] == 0.01
    with pytest.raises(UserFacingError, match=r"\[sensors.base\] sensitivity: expected a number >= 0.5"):
        config(base='url = "socket://x:1"\nsensitivity = 0')


def test_check_rig_passes_on_the_simulated_rig(capsys):
    assert main(["check-rig", "--sim-speed", "0"]) == 0
    out = capsys.readouterr().out
    assert "sensor_base" in out and "SIM-LKG5001" in out and "SIM33521B" in out and out.rstrip().endswith("PASS")
    assert main(["check-rig", "--sim-speed", "0", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["passed"] and report["reasons"] == []
    assert set(report["identities"]) == {"generator", "amplifier", "sensor_base", "sensor_tip"}
    assert report["agreement"]["deviation"] < 0.01
    assert report["sensors"]["base"]["amplitude_m"] > 1e-5


def test_check_rig_fails_with_the_reason_when_a_sensitivity_is_off_by_10_percent(tmp_path, capsys):
    sim = tmp_path / "sim.toml"
    sim.write_text("[effects]\ntip_scale_error = 0.1\n")
    assert main(["check-rig", "--sim-speed", "0", "--sim-config", str(sim), "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert not report["passed"]
    assert report["agreement"]["ratio"] == pytest.approx(1.10, abs=0.005)
    assert "the sensors disagree: tip / base amplitude = 1.10" in report["reasons"][0]
    assert "agreement_tolerance 5 %" in report["reasons"][0]
    assert main(["check-rig", "--sim-speed", "0", "--sim-config", str(sim)]) == 1
    assert "FAIL: the sensors disagree" in capsys.readouterr().out
    # the declared sensitivity corrects it: the check passes again
    rig = tmp_path / "rig.toml"
    shipped = DEFAULT_RIG_PATH.read_text()
    tip = shipped.index("[sensors.tip]")
    rig.write_text(shipped[:tip] + shipped[tip:].replace("sensitivity = 1.0", "sensitivity = 0.90909091", 1))
    assert main(["check-rig", "--sim-speed", "0", "--sim-config", str(sim), "--config", str(rig),
                 "--simulated"]) == 0


def test_check_rig_names_an_unreachable_instrument(tmp_path, capsys):
    rig = tmp_path / "rig.toml"
    rig.write_text(DEFAULT_RIG_PATH.read_text().replace('url = "socket://127.0.0.1:5025"',
                                                        'url = "socket://127.0.0.1:1"'))
    assert main(["check-rig", "--config", str(rig), "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert "cannot reach the instruments" in report["reasons"][0] and "signal generator" in report["reasons"][0]


# ---- GUI start-up check --------------------------------------------------------------------------------
def test_a_missing_qt_platform_library_gives_one_line_naming_the_package(monkeypatch, capsys):
    from rig.gui import startup

    present_and_absent = {"libc.so.6": "libc6", "libshakerlab-absent-xcb-cursor.so.0": "libxcb-cursor0"}
    line = startup.problem(present_and_absent, environ={"DISPLAY": ":0"})
    assert "sudo apt-get install libxcb-cursor0 " in line and "libc6" not in line
    assert startup.problem(present_and_absent, environ={"DISPLAY": ":0", "QT_QPA_PLATFORM": "offscreen"}) is None
    assert startup.problem(present_and_absent, environ={}) is None  # no display: the existing message
    assert set(startup.XCB_LIBRARIES.values()) >= {"libxcb-cursor0", "libxcb-icccm4", "libxcb-keysyms1"}
    # through the command: exit 2 and the one line, before Qt is loaded
    monkeypatch.setitem(startup.XCB_LIBRARIES, "libshakerlab-absent-xcb-cursor.so.0", "libxcb-cursor0")
    monkeypatch.setenv("DISPLAY", ":0")
    monkeypatch.delenv("QT_QPA_PLATFORM", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["gui"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "libxcb-cursor0" in err[0] and err[0].startswith("shakerlab gui: error:")


def test_the_configs_in_the_real_rig_guide_are_valid():
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "real-rig.md").read_text()
    blocks = re.findall(r"```toml\n(.*?)```", text, re.S)
    full = tomllib.loads(blocks[0])
    cfg = parse_config(full, blocks[0], "real-rig.md")
    assert cfg.amplifier_kind == "manual" and cfg.data["sensors"]["base"]["baudrate"] == 9600
    modbus = tomllib.loads("\n".join(line[2:] for line in blocks[1].splitlines()))
    full["amplifier"] = modbus["amplifier"]
    assert parse_config(full, "", "real-rig.md").data["amplifier"]["registers"]["gain"] == 101
