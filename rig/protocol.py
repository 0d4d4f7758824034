"""The experiment protocol (TOML): what the rig does, stage by stage.

Stages, in this order (each recorded as its own stage of the run file):

1. ``linear``: a small harmonic off resonance (frequency, amplitude, duration).
2. ``resonance_search``: a stepped sine (coarse grid, then a fine grid around
   the peak) that locates the first resonance from the measured tip/base
   amplitude ratio.
3. ``nonlinear``: near the resonance, the amplitude is raised step by step;
   after each step the response is analysed and the raising stops at clear
   nonlinearity (harmonic distortion, a change of gain or of the loop's loss
   factor over its threshold) or when the next step would approach a limit;
   the last level is held for ``hold_s``.
4. ``validation`` (optional, any number, ``[[validation]]``): harmonics at
   other frequencies/amplitudes, given absolutely or relative to the
   resonance and to the nonlinear stage's final amplitude.

The shipped default is ``rig/default_protocol.toml``; every field is in
:data:`SCHEMA` and documented in ``docs/protocol.md``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from rig.messages import PRE_TRIGGER_S
from rig.safety import LimitError, Supervisor
from rig.control_plans import base_targets, check_amplitude_fields  # volts or base targets (rig.sine_control)
from shakerlab.errors import UserFacingError
from shakerlab.toml_fields import Field, load_toml, validate

DEFAULT_PROTOCOL_PATH = Path(__file__).with_name("default_protocol.toml")

_POS = dict(min=0.0, min_exclusive=True)


def _base_fields(what: str = "base displacement target") -> dict:
    """Closed-loop amplitude fields (rig.sine_control): base target and response ceilings."""
    return {
        "base_amplitude_mm": Field("number", None, **_POS,
                                   help=f"{what}: fundamental peak amplitude of the base motion (mm), held by "
                                        f"the sine controller (instead of amplitude_vpp)"),
        "max_tip_mm": Field("number", None, **_POS,
                            help="response limit (notching): the base target is lowered to keep the tip "
                                 "displacement's fundamental at or below this (mm)"),
        "max_relative_mm": Field("number", None, **_POS,
                                 help="response limit (notching) on the relative displacement y (mm)"),
    }

SCHEMA = {
    "run": {
        "settle_s": Field("number", 1.0, min=0.0,
                          help="rest (output off, not recorded) before each stage, so it starts near rest"),
        "pre_trigger_s": Field("number", PRE_TRIGGER_S, min=0.0, max=10.0,
                               help="recorded at the start of each stage with the output still off, before "
                                    "its drive goes on (whole acquisition blocks); 0: the record starts "
                                    "with the drive"),
    },
    "linear": {
        "frequency_hz": Field("number", **_POS, help="drive frequency, away from the resonance"),
        "amplitude_vpp": Field("number", None, **_POS,
                               help="generator amplitude (V peak-to-peak); or base_amplitude_mm"),
        "duration_s": Field("number", **_POS, help="time at the full amplitude (the ramps come on top)"),
        **_base_fields(),
    },
    "resonance_search": {
        "enabled": Field("bool", True, help="false: skip it (then give the nonlinear frequency in Hz)"),
        "method": Field("str", "stepped", choices=("stepped",), help="stepped sine"),
        "start_hz": Field("number", 5.0, **_POS, help="lowest frequency of the coarse grid"),
        "stop_hz": Field("number", 40.0, **_POS, help="highest frequency of the coarse grid"),
        "steps": Field("int", 16, min=3, max=1000, help="coarse grid points (geometric spacing)"),
        "refine_steps": Field("int", 8, min=0, max=1000,
                              help="fine grid points between the neighbours of the coarse peak"),
        "amplitude_vpp": Field("number", None, **_POS,
                               help="generator amplitude during the search (0.1 when neither this nor "
                                    "base_amplitude_mm is given)"),
        "settle_s": Field("number", 1.0, min=0.0, help="wait after each frequency change"),
        "measure_s": Field("number", 0.5, **_POS, help="analysed window at each frequency"),
        **_base_fields("base target held at every frequency"),
    },
    "nonlinear": {
        "frequency_hz": Field("number", None, **_POS, help="drive frequency (instead of frequency_factor)"),
        "frequency_factor": Field("number", 1.0, **_POS,
                                  help="drive frequency as a multiple of the resonance found by the search"),
        "start_vpp": Field("number", None, **_POS, help="first amplitude level (or start_base_mm)"),
        "step_factor": Field("number", 1.5, min=1.0, min_exclusive=True, max=4.0,
                             help="each level is this multiple of the previous one"),
        "max_vpp": Field("number", None, **_POS,
                         help="highest amplitude level (<= limits.max_generator_vpp; or max_base_mm)"),
        "start_base_mm": Field("number", None, **_POS,
                               help="first level as a base displacement target (mm, fundamental peak), "
                                    "instead of start_vpp"),
        "max_base_mm": Field("number", None, **_POS, help="highest base displacement target (mm), instead of max_vpp"),
        "max_tip_mm": _base_fields()["max_tip_mm"],
        "max_relative_mm": _base_fields()["max_relative_mm"],
        "dwell_s": Field("number", 1.5, **_POS, help="time at each level"),
        "analysis_s": Field("number", 0.75, **_POS, help="last part of each dwell that is analysed"),
        "settle_tolerance": Field("number", 0.0, min=0.0, max=0.5,
                                  help="judge a level only on a steady response: further analysis_s windows "
                                       "are recorded until two in a row give the same complex gain (relative "
                                       "over base displacement, fundamental) to this fraction; 0: the dwell "
                                       "alone decides"),
        "settle_max_s": Field("number", 20.0, **_POS,
                              help="longest extra wait at one level for settle_tolerance; then the level is "
                                   "judged as it is, with a warning"),
        "hold_s": Field("number", 2.0, min=0.0, help="extra time at the final level"),
        "thd_threshold": Field("number", 0.05, **_POS,
                               help="stop raising when the relative displacement's harmonic distortion exceeds this"),
        "gain_change_threshold": Field("number", 0.45, **_POS,
                                       help="stop raising when abs(gain / first gain - 1) exceeds this "
                                            "(gain = relative displacement over base displacement)"),
        "loss_change_threshold": Field("number", 1.0, **_POS,
                                       help="stop raising when the hysteresis loop's loss factor changed by "
                                            "more than this fraction of its first value"),
    },
}

VALIDATION_SCHEMA = {
    "name": Field("str", None, help="stage name; default validation, validation_2, ..."),
    "frequency_hz": Field("number", None, **_POS, help="drive frequency (or frequency_factor)"),
    "frequency_factor": Field("number", None, **_POS, help="drive frequency as a multiple of the resonance"),
    "amplitude_vpp": Field("number", None, **_POS, help="generator amplitude (or amplitude_fraction)"),
    "amplitude_fraction": Field("number", None, **_POS,
                                help="amplitude as a fraction of the nonlinear stage's final level"),
    "duration_s": Field("number", **_POS, help="time at the full amplitude"),
    **_base_fields(),
}


@dataclass
class Protocol:
    """A validated protocol: ``data`` mirrors the TOML, ``validation`` is the list of validation stages."""

    data: dict
    validation: list[dict]
    text: str
    source: str

    def __getitem__(self, table: str) -> dict:
        return self.data[table]

    def check_against_limits(self, limits: dict, config_source: str = "rig config") -> None:
        """Refuse, before anything moves, every setpoint the protocol can produce beyond the rig's limits
        (the supervisor's own checks): amplitudes (``*_vpp``), drive frequencies (``*_hz``) and step
        durations (``*_s``) of every table; a frequency_factor over the whole range the resonance can
        take (the search's start_hz..stop_hz); an amplitude_fraction of the highest final level of
        the nonlinear stage (its max_vpp)."""
        supervisor = Supervisor(limits)
        check_by_suffix = {"_vpp": supervisor.check_amplitude, "_hz": supervisor.check_frequency,
                           "_s": supervisor.check_duration}
        search = self.data["resonance_search"]
        highest_level = self.data["nonlinear"]["max_vpp"]
        tables = [(name, values) for name, values in self.data.items()
                  if name != "resonance_search" or search["enabled"]]
        tables += [(f"validation #{i + 1}", v) for i, v in enumerate(self.validation)]
        for table, values in tables:
            checks = [(key, value, check) for key, value in values.items() for suffix, check in check_by_suffix.items()
                      if key.endswith(suffix) and isinstance(value, float)]
            factor = values.get("frequency_factor")
            if factor is not None and values.get("frequency_hz") is None:
                for end in ("start_hz", "stop_hz"):
                    checks.append((f"frequency_factor ({factor:g} x [resonance_search] {end} {search[end]:g} Hz)",
                                   factor * search[end], supervisor.check_frequency))
            fraction = values.get("amplitude_fraction")
            if fraction is not None and highest_level is not None:
                checks.append((f"amplitude_fraction ({fraction:g} x [nonlinear] max_vpp {highest_level:g} V)",
                               fraction * highest_level, supervisor.check_amplitude))
            for key, value, check in checks:
                try:
                    check(value)
                except LimitError as exc:
                    raise UserFacingError(f"{self.source}: [{table}] {key} = {value:g}: {exc} ({config_source})") from None
        bmax = limits["max_base_displacement_m"]
        for table, key, value in base_targets(self):
            if value >= bmax:
                raise UserFacingError(
                    f"{self.source}: [{table}] {key} = {value * 1e3:g} mm reaches the rig's limit "
                    f"max_base_displacement_m = {bmax * 1e3:g} mm ({config_source})"
                )


def parse_protocol(data: dict, text: str = "", source: str = "protocol.toml") -> Protocol:
    raw = dict(data)
    validation_raw = raw.pop("validation", [])
    if isinstance(validation_raw, dict):
        validation_raw = [validation_raw]
    if not isinstance(validation_raw, list):
        raise UserFacingError(f"{source}: validation must be a list of tables ([[validation]])")
    cfg = validate(raw, SCHEMA, source)
    nl = cfg["nonlinear"]
    search = cfg["resonance_search"]
    if search["stop_hz"] <= search["start_hz"]:
        raise UserFacingError(
            f"{source}: [resonance_search] stop_hz ({search['stop_hz']:g}) must exceed start_hz ({search['start_hz']:g})"
        )
    if nl["max_vpp"] is not None and nl["start_vpp"] is not None and nl["max_vpp"] < nl["start_vpp"]:
        raise UserFacingError(f"{source}: [nonlinear] max_vpp ({nl['max_vpp']:g}) is below start_vpp ({nl['start_vpp']:g})")
    if nl["analysis_s"] > nl["dwell_s"]:
        raise UserFacingError(f"{source}: [nonlinear] analysis_s ({nl['analysis_s']:g}) exceeds dwell_s ({nl['dwell_s']:g})")
    if nl["frequency_hz"] is None and not search["enabled"]:
        raise UserFacingError(
            f"{source}: [nonlinear] frequency_hz: needed when [resonance_search] enabled = false "
            f"(frequency_factor is relative to the resonance the search finds)"
        )
    validation = []
    names = set()
    for i, v in enumerate(validation_raw):
        table = f"validation #{i + 1}"
        if not isinstance(v, dict):
            raise UserFacingError(f"{source}: [[validation]] #{i + 1} must be a table")
        v = validate(v, VALIDATION_SCHEMA, source, table)
        if (v["frequency_hz"] is None) == (v["frequency_factor"] is None):
            raise UserFacingError(f"{source}: [{table}] give exactly one of frequency_hz and frequency_factor")
        if v["base_amplitude_mm"] is not None and (v["amplitude_vpp"], v["amplitude_fraction"]) != (None, None):
            raise UserFacingError(f"{source}: [{table}] give base_amplitude_mm or one of amplitude_vpp and "
                                  f"amplitude_fraction, not both")
        if v["base_amplitude_mm"] is None and (v["amplitude_vpp"] is None) == (v["amplitude_fraction"] is None):
            raise UserFacingError(f"{source}: [{table}] give exactly one of amplitude_vpp and amplitude_fraction "
                                  f"(or base_amplitude_mm)")
        if v["frequency_factor"] is not None and not search["enabled"]:
            raise UserFacingError(f"{source}: [{table}] frequency_factor needs the resonance search (enabled = false)")
        if v["name"] is None:
            v["name"] = "validation" if i == 0 else f"validation_{i + 1}"
        if not v["name"].startswith("validation") or not v["name"].replace("_", "").isalnum():
            raise UserFacingError(
                f"{source}: [{table}] name: {v['name']!r} must start with 'validation' and hold only letters, "
                f"digits and '_'"
            )
        if v["name"] in names:
            raise UserFacingError(f"{source}: [{table}] name: {v['name']!r} is used twice")
        names.add(v["name"])
        validation.append(v)
    check_amplitude_fields(cfg, validation, source)
    return Protocol(cfg, validation, text, source)


def load_protocol(path: str | Path | None = None) -> Protocol:
    """Load a protocol file (or the shipped default when ``path`` is None)."""
    path = DEFAULT_PROTOCOL_PATH if path is None else Path(path)
    data, text = load_toml(path, "protocol")
    return parse_protocol(data, text, str(path))
