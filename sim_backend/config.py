"""Configuration of the simulated rig: the shipped defaults merged with user overrides.

``load_config(None)`` returns the defaults from ``default_sim.toml``; a dict or a
TOML file path overrides any subset of its tables/keys.  The schema is the
defaults themselves (every value a finite number; the fields below must be
positive or non-negative), checked by :mod:`shakerlab.toml_fields` like the rig
config and the protocol: unknown tables or keys and non-numeric or
out-of-range values raise :class:`UserFacingError` naming the source, the table
and the field.
"""
from __future__ import annotations

import tomllib
from pathlib import Path

from shakerlab.errors import UserFacingError
from shakerlab.toml_fields import Field, load_toml, validate

DEFAULT_CONFIG_PATH = Path(__file__).with_name("default_sim.toml")

POSITIVE_FIELDS = {
    ("clock", "sample_rate"), ("clock", "lockstep_block_s"), ("clock", "ring_seconds"),
    ("specimen", "mass"), ("shaker", "armature_mass"), ("shaker", "force_constant"),
    ("shaker", "coil_resistance"), ("amplifier", "transconductance"), ("amplifier", "max_gain"),
    ("amplifier", "max_current_limit"), ("amplifier", "current_limit"),
    ("amplifier", "rail_voltage"), ("amplifier", "thermal_resistance"),
    ("amplifier", "thermal_time_constant"), ("sensors", "range"), ("sensors", "resolution"),
    ("sensors", "velocity_range"),
}
NON_NEGATIVE_FIELDS = {
    ("specimen", "c_m"), ("shaker", "suspension_stiffness"), ("shaker", "suspension_damping"),
    ("amplifier", "watchdog_timeout"), ("sensors", "noise_std"), ("sensors", "velocity_noise_std"),
    ("effects", "coulomb_friction"), ("effects", "contact_stiffness"), ("effects", "channel_delay"),
    ("effects", "higher_mode_frequency"), ("effects", "higher_mode_damping"), ("sensors", "tip_on_base"),
}


def default_config() -> dict:
    with open(DEFAULT_CONFIG_PATH, "rb") as fh:
        return tomllib.load(fh)


def _schema(defaults: dict, path: tuple = ()) -> dict:
    """The defaults as a schema: every value a finite number, some positive or non-negative."""
    schema = {}
    for key, value in defaults.items():
        where = (*path, key)
        if isinstance(value, dict):
            schema[key] = _schema(value, where)
        elif where in POSITIVE_FIELDS:
            schema[key] = Field("number", value, min=0.0, min_exclusive=True)
        elif where in NON_NEGATIVE_FIELDS:
            schema[key] = Field("number", value, min=0.0)
        else:
            schema[key] = Field("number", value)
    return schema


SCHEMA = _schema(default_config())


def load_config(config: dict | str | Path | None = None) -> dict:
    """Return the full, validated simulator configuration."""
    if config is None:
        source, override = "default_sim.toml", {}
    elif isinstance(config, dict):
        source, override = "simulator config", config
    else:
        source = str(config)
        override, _ = load_toml(config, "simulator config")
    cfg = validate(override, SCHEMA, source)
    _cross_check(cfg, source)
    return cfg


def _cross_check(cfg: dict, source: str) -> None:
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
    if cfg["sensors"]["tip_on_base"] not in (0.0, 1.0):
        raise UserFacingError(f"{source}: sensors.tip_on_base: expected 0 (tip sensor on the tip) or 1 (on the "
                              f"base), got {cfg['sensors']['tip_on_base']!r}")
    if cfg["effects"]["contact_stiffness"] > 0 and cfg["effects"]["contact_gap"] <= 0:
        raise UserFacingError(f"{source}: effects.contact_gap must be > 0 when contact_stiffness is set")
