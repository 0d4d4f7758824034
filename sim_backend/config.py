"""Configuration of the simulated rig: the shipped defaults merged with user overrides.

``load_config(None)`` returns the defaults from ``default_sim.toml``; a dict or a
TOML file path overrides any subset of its tables/keys.  Unknown tables or keys
and non-numeric or out-of-range values raise :class:`UserFacingError` naming the
source and the field.
"""
from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path

from shakerlab.errors import UserFacingError

DEFAULT_CONFIG_PATH = Path(__file__).with_name("default_sim.toml")

# fields that must be strictly positive
_POSITIVE = {
    ("clock", "sample_rate"), ("clock", "lockstep_block_s"), ("clock", "ring_seconds"),
    ("specimen", "mass"), ("shaker", "armature_mass"), ("shaker", "force_constant"),
    ("shaker", "coil_resistance"), ("amplifier", "transconductance"), ("amplifier", "max_gain"),
    ("amplifier", "max_current_limit"), ("amplifier", "current_limit"),
    ("amplifier", "rail_voltage"), ("amplifier", "thermal_resistance"),
    ("amplifier", "thermal_time_constant"), ("sensors", "range"), ("sensors", "resolution"),
}
# fields that must be >= 0
_NON_NEGATIVE = {
    ("specimen", "c_m"), ("shaker", "suspension_stiffness"), ("shaker", "suspension_damping"),
    ("amplifier", "watchdog_timeout"), ("sensors", "noise_std"),
    ("effects", "coulomb_friction"), ("effects", "contact_stiffness"), ("effects", "channel_delay"),
    ("effects", "higher_mode_frequency"), ("effects", "higher_mode_damping"),
}


def default_config() -> dict:
    with open(DEFAULT_CONFIG_PATH, "rb") as fh:
        return tomllib.load(fh)


def _merge(base: dict, override: dict, source: str, prefix: str = "") -> None:
    for key, value in override.items():
        where = f"{prefix}{key}"
        if key not in base:
            known = ", ".join(sorted(base))
            raise UserFacingError(f"{source}: unknown simulator setting {where!r} (known here: {known})")
        if isinstance(base[key], dict):
            if not isinstance(value, dict):
                raise UserFacingError(f"{source}: {where!r} must be a table")
            _merge(base[key], value, source, where + ".")
        else:
            base[key] = value


def load_config(config: dict | str | Path | None = None) -> dict:
    """Return the full, validated simulator configuration."""
    cfg = default_config()
    if config is None:
        source, override = "default_sim.toml", {}
    elif isinstance(config, dict):
        source, override = "simulator config", copy.deepcopy(config)
    else:
        path = Path(config)
        source = str(path)
        try:
            with open(path, "rb") as fh:
                override = tomllib.load(fh)
        except FileNotFoundError:
            raise UserFacingError(f"simulator config file {path} does not exist") from None
        except tomllib.TOMLDecodeError as exc:
            raise UserFacingError(f"{path}: not valid TOML: {exc}") from None
    _merge(cfg, override, source)
    _validate(cfg, source)
    return cfg


def _validate(cfg: dict, source: str) -> None:
    def check(table: str, key: str, value) -> None:
        name = f"{table}.{key}"
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise UserFacingError(f"{source}: {name} must be a finite number, got {value!r}")
        if (table, key) in _POSITIVE and value <= 0:
            raise UserFacingError(f"{source}: {name} must be > 0, got {value!r}")
        if (table, key) in _NON_NEGATIVE and value < 0:
            raise UserFacingError(f"{source}: {name} must be >= 0, got {value!r}")

    for table, values in cfg.items():
        for key, value in values.items():
            if isinstance(value, dict):
                for sub, v in value.items():
                    check(f"{table}.{key}", sub, v)
            else:
                check(table, key, value)
    amp = cfg["amplifier"]
    if amp["current_limit"] > amp["max_current_limit"]:
        raise UserFacingError(f"{source}: amplifier.current_limit exceeds amplifier.max_current_limit")
    if amp["max_temperature"] <= amp["ambient_temperature"]:
        raise UserFacingError(f"{source}: amplifier.max_temperature must exceed ambient_temperature")
    sp = cfg["specimen"]
    if sp["gamma"] + sp["delta"] <= 0:
        raise UserFacingError(f"{source}: specimen.gamma + specimen.delta must be > 0 (bounded hysteresis)")
    if sp["k_m"] + sp["alpha_m"] <= 0:
        raise UserFacingError(f"{source}: specimen.k_m + specimen.alpha_m must be > 0")
    fs = cfg["clock"]["sample_rate"]
    f2 = cfg["effects"]["higher_mode_frequency"]
    if f2 >= fs / 10:
        raise UserFacingError(
            f"{source}: effects.higher_mode_frequency {f2} Hz is too close to Nyquist for "
            f"clock.sample_rate {fs} Hz (keep it below sample_rate/10)"
        )
    if cfg["effects"]["contact_stiffness"] > 0 and cfg["effects"]["contact_gap"] <= 0:
        raise UserFacingError(f"{source}: effects.contact_gap must be > 0 when contact_stiffness is set")
