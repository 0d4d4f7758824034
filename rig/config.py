"""The rig configuration (``rig.toml``): instrument addresses, limits, acquisition.

Switching from the simulated rig to the real one changes only the addresses.
The shipped ``rig/default_rig.toml`` holds limits and acquisition settings
that suit the simulated rig; ``shakerlab acquire`` without ``--config`` uses
it with the addresses of the simulated rig it starts. Every field is
documented in ``docs/acquisition.md`` (generated from :data:`SCHEMA`).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

from drivers.line_link import BAUD_RATES, DATA_BITS, FLOW_CONTROLS, PARITIES, STOP_BITS, TERMINATIONS
from drivers.visa_link import VISA_LIBRARIES, is_visa_resource
from shakerlab.errors import UserFacingError
from shakerlab.toml_fields import Field, load_toml, validate

DEFAULT_RIG_PATH = Path(__file__).with_name("default_rig.toml")
# The highest drive frequency leaves this many samples per period: the analysis fits five harmonics,
# the fifth then sits at half the sensors' Nyquist frequency.
SAMPLES_PER_PERIOD = 20

AMPLIFIER_KINDS = ("shakerlab", "modbus", "manual")


def serial_fields(termination: str) -> dict:
    """An instrument's serial line settings (used on a serial device, a pty or an ASRL resource)."""
    return {
        "baudrate": Field("int", 115200, choices=BAUD_RATES, help="serial baud rate [bit/s]"),
        "data_bits": Field("int", 8, choices=tuple(DATA_BITS), help="serial data bits"),
        "parity": Field("str", "none", choices=tuple(PARITIES), help="serial parity"),
        "stop_bits": Field("number", 1.0, choices=tuple(float(k) for k in STOP_BITS), help="serial stop bits"),
        "flow_control": Field("str", "none", choices=FLOW_CONTROLS,
                              help="serial flow control: none, xonxoff (software), rtscts or dsrdtr (hardware)"),
        "read_termination": Field("str", termination, choices=TERMINATIONS,
                                  help="end of each reply (\\n, \\r or \\r\\n)"),
        "write_termination": Field("str", termination, choices=TERMINATIONS,
                                   help="end of each command (\\n, \\r or \\r\\n)"),
    }


def sensor_fields(point: str) -> dict:
    return {
        "url": Field("str", help=f"pyserial URL of the {point} laser sensor"),
        "timeout_s": Field("number", 1.0, min=0, min_exclusive=True, help="reply timeout [s]"),
        "quantity": Field("str", "displacement", choices=("displacement", "velocity"),
                          help=f"what the {point} sensor reports (its measuring mode, set at start and read "
                               f"back): displacement [m] or velocity [m/s]; velocity is integrated in real "
                               f"time for the displacement limits and the plans' decisions, and recorded as "
                               f"measured (v_{point})"),
        "sensitivity": Field("number", 1.0, min=0.5, max=2.0,
                             help="calibration factor: true motion = sensitivity x the controller's reading "
                                  "(1 = the reading is exact; the factor of the sensor's calibration "
                                  "certificate for the range in use); applied to every sample and recorded"),
        "range_m": Field("number", None, min=0, min_exclusive=True,
                         help="half measuring range the sensor must have [m, or m/s in velocity mode]; "
                              "checked against the range the controller reports (omit: not checked)"),
        "serial_number": Field("str", "", help="the sensor head's serial number (recorded in the run file; "
                                               "check-rig compares it with the identity when the controller "
                                               "reports one)"),
        "calibration_date": Field("str", "", help="date of the calibration certificate (recorded as given)"),
        **serial_fields("\r"),
    }


SCHEMA = {
    "generator": {
        "url": Field("str", None, help="pyserial URL of the SCPI signal generator (socket://host:port, /dev/ttyUSB0, "
                                       "a pty path); give this or resource"),
        "resource": Field("str", None, help="VISA resource string of the generator (TCPIP0::192.168.1.20::5025::SOCKET, "
                                            "TCPIP0::host::inst0::INSTR, USB0::0x0957::0x2C07::MY1234::INSTR, "
                                            "GPIB0::10::INSTR, ASRL/dev/ttyUSB0::INSTR); give this or url"),
        "visa_library": Field("str", "", choices=VISA_LIBRARIES,
                              help="with resource: '' = NI-VISA or Keysight VISA when installed, else pyvisa-py; "
                                   "'@py' = pyvisa-py; '@ivi' = the vendor library"),
        "timeout_s": Field("number", 1.0, min=0, min_exclusive=True, help="reply timeout [s]"),
        **serial_fields("\n"),
    },
    "amplifier": {
        "kind": Field("str", "shakerlab", choices=AMPLIFIER_KINDS,
                      help="'shakerlab': Modbus TCP with the register map of docs/protocols.md; 'modbus': Modbus "
                           "TCP with the map declared in [amplifier.registers]; 'manual': no remote control, the "
                           "gain is set on the front panel (the supervisor stops the generator instead of muting "
                           "the amplifier)"),
        "address": Field("str", None, help="Modbus TCP address of the power amplifier, host:port (not with "
                                           "kind = 'manual')"),
        "device_id": Field("int", 1, min=0, max=247, help="Modbus device (unit) id"),
        "timeout_s": Field("number", 1.0, min=0, min_exclusive=True, help="reply timeout [s]"),
        "gain": Field("number", 1.0, min=0, min_exclusive=True,
                      help="amplifier gain used for the whole run (set while the output is off); with "
                           "kind = 'manual' required: the gain the operator set on the front panel"),
        "current_limit_a": Field("number", 5.0, min=0, min_exclusive=True,
                                 help="the amplifier's own over-current trip level [A], set at start "
                                      "(kind = 'shakerlab')"),
        "watchdog_timeout_s": Field("number", 1.0, min=0.05, max=60,
                                    help="comms watchdog [s]: the amplifier mutes when the controller is silent "
                                         "this long (kind = 'shakerlab', or 'modbus' with a watchdog register)"),
        "registers": {
            "enable": Field("int", None, min=0, max=65535,
                            help="register that mutes / enables the output (required with kind = 'modbus')"),
            "enable_on": Field("int", 1, min=0, max=65535, help="value written to enable the output"),
            "enable_off": Field("int", 0, min=0, max=65535, help="value written to mute the output"),
            "gain": Field("int", None, min=0, max=65535,
                          help="gain register (omit when the gain is set on the front panel)"),
            "gain_scale": Field("number", 1.0, min=0, min_exclusive=True, help="raw = gain x gain_scale"),
            "gain_max": Field("number", None, min=0, min_exclusive=True,
                              help="the highest gain the amplifier accepts (required with a gain register)"),
            "watchdog": Field("int", None, min=0, max=65535, help="comms-watchdog timeout register"),
            "watchdog_scale": Field("number", 1000.0, min=0, min_exclusive=True,
                                    help="raw = timeout [s] x watchdog_scale (1000: milliseconds)"),
            "heartbeat": Field("int", None, min=0, max=65535,
                               help="register written periodically for the watchdog (omit: ENABLE is read "
                                    "instead)"),
            "current": Field("int", None, min=0, max=65535, help="measured output current register"),
            "current_scale": Field("number", 1000.0, min=0, min_exclusive=True,
                                   help="A = raw / current_scale (1000: milliamperes)"),
            "current_signed": Field("bool", True, help="the current register is a signed 16-bit value"),
            "status": Field("int", None, min=0, max=65535, help="status register holding fault bits"),
            "fault_bits": Field("int", 65535, min=1, max=65535,
                                help="mask of the status bits that mean a fault (a set bit trips the run)"),
            "fault_reset": Field("int", None, min=0, max=65535,
                                 help="register written 1 to clear latched faults"),
            "ident": Field("int", None, min=0, max=65535,
                           help="first register of an ASCII identity (two characters per register)"),
            "ident_registers": Field("int", 16, min=1, max=64, help="number of identity registers"),
        },
    },
    "sensors": {
        "base": sensor_fields("base"),
        "tip": sensor_fields("tip"),
    },
    "acquisition": {
        "sample_rate_hz": Field("number", 10000.0, min=1, max=1e6, help="sensor sampling rate (both channels)"),
        "block_s": Field("number", 0.05, min=0.001, max=1.0,
                         help="samples are fetched, supervised and recorded in blocks this long"),
        "flush_interval_s": Field("number", 0.5, min=0.01, max=1.0,
                                  help="the run file is flushed to disk at least this often"),
        "stall_timeout_s": Field("number", 2.0, min=0.1,
                                 help="the heartbeat stops (so the amplifier watchdog mutes) when the runner "
                                      "has not made progress for this long"),
    },
    "check": {
        "tone_hz": Field("number", 20.0, min=0, min_exclusive=True,
                         help="check-rig: frequency of the calibration tone [Hz] (<= limits.max_drive_frequency_hz)"),
        "tone_vpp": Field("number", 0.2, min=0.001,
                          help="check-rig: generator amplitude of the calibration tone [Vpp] "
                               "(<= limits.max_generator_vpp)"),
        "settle_s": Field("number", 0.5, min=0, max=60,
                          help="check-rig: time the tone runs before the measuring window [s]"),
        "duration_s": Field("number", 2.0, min=0.1, max=60, help="check-rig: measuring window [s]"),
        "min_amplitude_m": Field("number", 1e-6, min=0, min_exclusive=True,
                                 help="check-rig fails when the base sensor sees less motion than this [m]"),
        "agreement_tolerance": Field("number", 0.05, min=0, min_exclusive=True, max=1,
                                     help="check-rig fails when the two sensors' amplitudes (both on the base) "
                                          "differ by more than this fraction"),
    },
    "limits": {
        "max_generator_vpp": Field("number", min=0, min_exclusive=True,
                                   help="highest generator amplitude (V peak-to-peak); also set as the "
                                        "generator's own voltage limit"),
        "max_amplifier_gain": Field("number", min=0, min_exclusive=True, help="highest amplifier gain"),
        "max_base_displacement_m": Field("number", min=0, min_exclusive=True,
                                         help="trip when abs(x_base - rest reading) exceeds this"),
        "max_tip_displacement_m": Field("number", min=0, min_exclusive=True,
                                        help="trip when abs(x_tip - rest reading) exceeds this"),
        "max_amplifier_current_a": Field("number", min=0, min_exclusive=True,
                                         help="trip when the amplifier's measured output current exceeds this"),
        "ramp_rate_vpp_per_s": Field("number", 1.0, min=0, min_exclusive=True,
                                     help="amplitude changes are ramped at this rate, never stepped"),
        "abort_ramp_s": Field("number", 0.5, min=0, min_exclusive=True, max=30,
                              help="on abort, error or trip the output ramps from its level to zero in this time"),
        "max_drive_frequency_hz": Field("number", None, min=0, min_exclusive=True,
                                        help="highest drive frequency; default and upper bound: "
                                             "acquisition.sample_rate_hz / 20 (the fifth harmonic the analysis "
                                             "fits stays at half the sensors' Nyquist frequency)"),
        "max_step_duration_s": Field("number", 3600.0, min=0, min_exclusive=True,
                                     help="longest time of any one protocol step (a duration, dwell, hold, "
                                          "settle or measuring window)"),
        "soft_limit_fraction": Field("number", 0.8, min=0.1, max=1.0,
                                     help="the nonlinear stage stops raising when the next step's predicted "
                                          "response exceeds this fraction of a limit"),
    },
}


@dataclass
class RigConfig:
    """A validated rig configuration (``data`` mirrors the TOML tables) and its source text."""

    data: dict
    text: str
    source: str

    @property
    def limits(self) -> dict:
        return self.data["limits"]

    @property
    def acquisition(self) -> dict:
        return self.data["acquisition"]

    @property
    def quantities(self) -> dict:
        """What each sensor reports: {"base": "displacement"|"velocity", "tip": ...}."""
        return {k: self.data["sensors"][k]["quantity"] for k in ("base", "tip")}

    @property
    def amplifier_kind(self) -> str:
        return self.data["amplifier"]["kind"]

    def addresses(self) -> dict:
        d = self.data
        return {"generator": d["generator"]["resource"] or d["generator"]["url"],
                "amplifier": d["amplifier"]["address"] or "manual (no remote control)",
                "sensor_base": d["sensors"]["base"]["url"], "sensor_tip": d["sensors"]["tip"]["url"]}

    def with_addresses(self, addresses: dict) -> "RigConfig":
        """The same settings with other instrument addresses (e.g. a simulated rig's). A manual amplifier
        stays manual (its gain is then entered on the simulated amplifier at start)."""
        data = copy.deepcopy(self.data)
        data["generator"]["url"] = addresses["generator"]
        data["generator"]["resource"] = None
        if data["amplifier"]["kind"] != "manual":
            data["amplifier"]["address"] = addresses["amplifier"]
        data["sensors"]["base"]["url"] = addresses["sensor_base"]
        data["sensors"]["tip"]["url"] = addresses["sensor_tip"]
        lines = [f"# addresses replaced by the simulated rig's: {addresses}", self.text]
        return RigConfig(data, "\n".join(lines), self.source)


def parse_config(data: dict, text: str = "", source: str = "rig.toml") -> RigConfig:
    cfg = validate(data, SCHEMA, source)
    lim = cfg["limits"]
    if cfg["amplifier"]["gain"] > lim["max_amplifier_gain"]:
        raise UserFacingError(
            f"{source}: [amplifier] gain: {cfg['amplifier']['gain']:g} exceeds [limits] max_amplifier_gain "
            f"{lim['max_amplifier_gain']:g}"
        )
    highest_drive_hz = cfg["acquisition"]["sample_rate_hz"] / SAMPLES_PER_PERIOD
    if lim["max_drive_frequency_hz"] is None:
        lim["max_drive_frequency_hz"] = highest_drive_hz
    elif lim["max_drive_frequency_hz"] > highest_drive_hz:
        raise UserFacingError(
            f"{source}: [limits] max_drive_frequency_hz: {lim['max_drive_frequency_hz']:g} Hz exceeds "
            f"[acquisition] sample_rate_hz / {SAMPLES_PER_PERIOD} = {highest_drive_hz:g} Hz"
        )
    _check_generator(cfg["generator"], source)
    _check_amplifier(cfg["amplifier"], data.get("amplifier", {}), source)
    chk = cfg["check"]
    if chk["tone_vpp"] > lim["max_generator_vpp"]:
        raise UserFacingError(f"{source}: [check] tone_vpp: {chk['tone_vpp']:g} Vpp exceeds [limits] "
                              f"max_generator_vpp {lim['max_generator_vpp']:g} Vpp")
    if chk["tone_hz"] > lim["max_drive_frequency_hz"]:
        raise UserFacingError(f"{source}: [check] tone_hz: {chk['tone_hz']:g} Hz exceeds [limits] "
                              f"max_drive_frequency_hz {lim['max_drive_frequency_hz']:g} Hz")
    return RigConfig(cfg, text, source)


def _check_generator(gen: dict, source: str) -> None:
    if (gen["url"] is None) == (gen["resource"] is None):
        raise UserFacingError(f"{source}: [generator]: give exactly one of url (a pyserial URL) and resource "
                              f"(a VISA resource string)")
    if gen["resource"] is not None and not is_visa_resource(gen["resource"]):
        raise UserFacingError(f"{source}: [generator] resource: {gen['resource']!r} is not a VISA resource string "
                              f"(TCPIP0::host::5025::SOCKET, TCPIP0::host::inst0::INSTR, USB0::...::INSTR, "
                              f"GPIB0::10::INSTR, ASRL/dev/ttyUSB0::INSTR)")
    if gen["url"] is not None and is_visa_resource(gen["url"]):
        raise UserFacingError(f"{source}: [generator] url: {gen['url']!r} is a VISA resource string; give it as "
                              f"resource = {gen['url']!r}")


def _check_amplifier(amp: dict, raw: dict, source: str) -> None:
    kind = amp["kind"]
    declared = sorted(k for k, v in (raw.get("registers") or {}).items() if v is not None) \
        if isinstance(raw, dict) else []
    if kind == "manual":
        if amp["address"] is not None:
            raise UserFacingError(f"{source}: [amplifier] address: a manual amplifier has no remote control; "
                                  f"remove the address or set kind = 'shakerlab' or 'modbus'")
        if "gain" not in raw:
            raise UserFacingError(f"{source}: [amplifier] gain: missing; with kind = 'manual' give the gain the "
                                  f"operator set on the amplifier's front panel")
    elif amp["address"] is None:
        raise UserFacingError(f"{source}: [amplifier] address: missing (expected host:port of the Modbus TCP "
                              f"amplifier, or kind = 'manual')")
    elif ":" not in amp["address"]:
        raise UserFacingError(f"{source}: [amplifier] address: expected host:port, got {amp['address']!r}")
    regs = amp["registers"]
    if kind != "modbus" and declared:
        raise UserFacingError(f"{source}: [amplifier.registers] {declared[0]}: a register map applies only to "
                              f"kind = 'modbus' (kind is {kind!r})")
    if kind == "modbus":
        if regs["enable"] is None:
            raise UserFacingError(f"{source}: [amplifier.registers] enable: missing (the register that mutes the "
                                  f"output; required with kind = 'modbus')")
        if regs["enable_on"] == regs["enable_off"]:
            raise UserFacingError(f"{source}: [amplifier.registers] enable_on and enable_off must differ")
        if regs["gain"] is not None and regs["gain_max"] is None:
            raise UserFacingError(f"{source}: [amplifier.registers] gain_max: missing (the highest gain the gain "
                                  f"register accepts)")
        if regs["gain_max"] is not None and regs["gain_max"] * regs["gain_scale"] > 65535:
            raise UserFacingError(f"{source}: [amplifier.registers] gain_max: {regs['gain_max']:g} x gain_scale "
                                  f"{regs['gain_scale']:g} does not fit a 16-bit register")
        if regs["gain_max"] is not None and amp["gain"] > regs["gain_max"]:
            raise UserFacingError(f"{source}: [amplifier] gain: {amp['gain']:g} exceeds [amplifier.registers] "
                                  f"gain_max {regs['gain_max']:g}")
        if regs["watchdog"] is not None and amp["watchdog_timeout_s"] * regs["watchdog_scale"] > 65535:
            raise UserFacingError(f"{source}: [amplifier] watchdog_timeout_s: {amp['watchdog_timeout_s']:g} s x "
                                  f"watchdog_scale {regs['watchdog_scale']:g} does not fit a 16-bit register")


def load_config(path: str | Path | None = None) -> RigConfig:
    """Load ``rig.toml`` (or the shipped default when ``path`` is None)."""
    path = DEFAULT_RIG_PATH if path is None else Path(path)
    data, text = load_toml(path, "rig config")
    return parse_config(data, text, str(path))
