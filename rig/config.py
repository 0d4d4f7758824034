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

from shakerlab.errors import UserFacingError
from shakerlab.toml_fields import Field, load_toml, validate

DEFAULT_RIG_PATH = Path(__file__).with_name("default_rig.toml")
# The highest drive frequency leaves this many samples per period: the analysis fits five harmonics,
# the fifth then sits at half the sensors' Nyquist frequency.
SAMPLES_PER_PERIOD = 20

SCHEMA = {
    "generator": {
        "url": Field("str", help="pyserial URL of the SCPI signal generator (socket://host:port, /dev/ttyUSB0, ...)"),
        "timeout_s": Field("number", 1.0, min=0, min_exclusive=True, help="reply timeout"),
    },
    "amplifier": {
        "address": Field("str", help="Modbus TCP address of the power amplifier, host:port"),
        "device_id": Field("int", 1, min=0, max=247, help="Modbus device (unit) id"),
        "timeout_s": Field("number", 1.0, min=0, min_exclusive=True, help="reply timeout"),
        "gain": Field("number", 1.0, min=0, min_exclusive=True,
                      help="amplifier gain used for the whole run (set while the output is off)"),
        "current_limit_a": Field("number", 5.0, min=0, min_exclusive=True,
                                 help="the amplifier's own over-current trip level, set at start"),
        "watchdog_timeout_s": Field("number", 1.0, min=0.05, max=60,
                                    help="comms watchdog: the amplifier mutes when the controller is silent this long"),
    },
    "sensors": {
        "base": {
            "url": Field("str", help="pyserial URL of the base laser sensor"),
            "timeout_s": Field("number", 1.0, min=0, min_exclusive=True, help="reply timeout"),
            "quantity": Field("str", "displacement", choices=("displacement", "velocity"),
                              help="what the base sensor reports (its measuring mode, set at start and read "
                                   "back): displacement [m] or velocity [m/s]; velocity is integrated in real "
                                   "time for the displacement limits and the plans' decisions, and recorded as "
                                   "measured (v_base)"),
        },
        "tip": {
            "url": Field("str", help="pyserial URL of the tip laser sensor"),
            "timeout_s": Field("number", 1.0, min=0, min_exclusive=True, help="reply timeout"),
            "quantity": Field("str", "displacement", choices=("displacement", "velocity"),
                              help="what the tip sensor reports (its measuring mode, set at start and read "
                                   "back): displacement [m] or velocity [m/s]; velocity is integrated in real "
                                   "time for the displacement limits and the plans' decisions, and recorded as "
                                   "measured (v_tip)"),
        },
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

    def addresses(self) -> dict:
        d = self.data
        return {"generator": d["generator"]["url"], "amplifier": d["amplifier"]["address"],
                "sensor_base": d["sensors"]["base"]["url"], "sensor_tip": d["sensors"]["tip"]["url"]}

    def with_addresses(self, addresses: dict) -> "RigConfig":
        """The same settings with other instrument addresses (e.g. a simulated rig's)."""
        data = copy.deepcopy(self.data)
        data["generator"]["url"] = addresses["generator"]
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
    if ":" not in cfg["amplifier"]["address"]:
        raise UserFacingError(f"{source}: [amplifier] address: expected host:port, got {cfg['amplifier']['address']!r}")
    return RigConfig(cfg, text, source)


def load_config(path: str | Path | None = None) -> RigConfig:
    """Load ``rig.toml`` (or the shipped default when ``path`` is None)."""
    path = DEFAULT_RIG_PATH if path is None else Path(path)
    data, text = load_toml(path, "rig config")
    return parse_config(data, text, str(path))
