"""Issue 15, items 1-4: every setpoint is checked against the rig's limits before anything is
driven (never clipped); setpoints derived at run time are refused where they are derived, the
output ramps down and the run says why; the final message says what was read back."""
import tomllib

import pytest

from rig.config import DEFAULT_RIG_PATH, load_config, parse_config
from rig.messages import BeginStage, CheckSetpoint
from rig.plans import protocol_plan
from rig.protocol import load_protocol, parse_protocol
from rig.safety import LimitError, Supervisor
from rig.session import acquire, simulated_rig
from shakerlab.cli import main
from shakerlab.errors import UserFacingError
from shakerlab.runfile.reader import read_events, read_info

from test_rig_acquisition import SMALL_PROTOCOL, Tape
from test_rig_plans import run_plan

SHORT_PROTOCOL = """
[run]
settle_s = 0.2
[linear]
frequency_hz = 8.0
amplitude_vpp = 0.3
duration_s = 0.5
[resonance_search]
enabled = false
[nonlinear]
frequency_hz = 12.0
start_vpp = 0.2
max_vpp = 0.3
dwell_s = 0.4
analysis_s = 0.2
hold_s = 0.0
[[validation]]
frequency_hz = 10.0
amplitude_fraction = 100.0
duration_s = 4.0
"""


def protocol_file(tmp_path, text=SMALL_PROTOCOL, **changes):
    data = tomllib.loads(text)
    for key, value in changes.items():
        table, field = key.split("__")
        (data[table][0] if isinstance(data[table], list) else data[table])[field] = value
    lines = []
    for table, values in data.items():
        for entry in values if isinstance(values, list) else [values]:
            lines.append(f"[[{table}]]" if isinstance(values, list) else f"[{table}]")
            lines += [f"{k} = {str(v).lower() if isinstance(v, bool) else repr(v)}" for k, v in entry.items()]
    path = tmp_path / "p.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def acquire_cli(tmp_path, capsys, protocol_path):
    out = tmp_path / "r.h5"
    status = main(["acquire", "--sim-speed", "0", "--protocol", str(protocol_path), "-o", str(out)])
    return status, capsys.readouterr().err, out


# ---- item 1: amplitudes are refused, never clipped ---------------------------------------------------

def test_issue15_1_amplitude_fraction_beyond_the_limit_is_refused_before_anything_starts(tmp_path, capsys):
    path = protocol_file(tmp_path, validation__frequency_factor=0.7, validation__amplitude_fraction=100.0,
                         validation__duration_s=4.0)
    status, err, out = acquire_cli(tmp_path, capsys, path)
    assert status == 2
    assert "[validation #1] amplitude_fraction (100 x [nonlinear] max_vpp 1 V) = 100" in err
    assert "exceeds limits.max_generator_vpp = 6 Vpp" in err
    assert "Traceback" not in err and not out.exists()


def test_issue15_1_a_derived_amplitude_is_refused_where_it_is_derived_and_the_run_says_why(tmp_path):
    """The run-time check behind the protocol check: a plan whose validation amplitude, derived from
    the nonlinear stage's final level, exceeds the limit stops the run before that stage begins."""
    unchecked = parse_protocol(tomllib.loads(SHORT_PROTOCOL), SHORT_PROTOCOL, "short")
    harmless = parse_protocol(tomllib.loads(SHORT_PROTOCOL.replace("amplitude_fraction = 100.0",
                                                                   "amplitude_fraction = 1.0")), "", "ok")
    tape = Tape()
    with simulated_rig(speed=None) as (sim, config):
        outcome = acquire(config, harmless, tmp_path / "run.h5", lockstep=True, observers=[tape],
                          plan=protocol_plan(unchecked, config.limits))
        assert not sim.world.is_driven()
    assert outcome.status == "tripped"
    assert outcome.reason.startswith("setpoint refused: [validation] drive 30 Vpp (amplitude_fraction 100 x the "
                                     "nonlinear final level 0.3 Vpp)")
    assert "exceeds limits.max_generator_vpp = 6 Vpp" in outcome.reason
    info = read_info(outcome.path)
    assert list(info["stages"]) == ["linear", "nonlinear"]  # validation never began
    amplitudes = tape.amplitudes()
    assert amplitudes.max() == pytest.approx(0.3) and amplitudes[-1] == 0.0
    last = read_events(outcome.path)[-1]["message"]
    assert "run tripped: setpoint refused" in last and "generator output off (read back)" in last


def test_issue15_1_plans_check_derived_setpoints_before_the_stage_begins():
    protocol = parse_protocol(tomllib.loads(SHORT_PROTOCOL), SHORT_PROTOCOL, "short")
    messages, _ = run_plan(protocol_plan(protocol, {"soft_limit_fraction": 0.8, "max_base_displacement_m": 1.0,
                                                    "max_tip_displacement_m": 1.0}))
    i = next(k for k, m in enumerate(messages) if isinstance(m, BeginStage) and m.name == "validation")
    check = [m for m in messages[:i] if isinstance(m, CheckSetpoint)][-1]
    assert check.vpp == pytest.approx(30.0) and check.hz == 10.0
    assert "amplitude_fraction 100" in check.origin


# ---- item 2: drive frequency bounded by the generator and the sensors' Nyquist frequency --------------

def test_issue15_2_drive_frequency_above_the_sensor_bound_exits_2_naming_the_field(tmp_path, capsys):
    status, err, out = acquire_cli(tmp_path, capsys, protocol_file(tmp_path, linear__frequency_hz=6000.0))
    assert status == 2
    assert "[linear] frequency_hz = 6000: drive frequency 6000 Hz exceeds limits.max_drive_frequency_hz = 500 Hz" in err
    assert "Traceback" not in err and not out.exists()


@pytest.mark.parametrize("changes,needle", [
    ({"linear__frequency_hz": 1e9}, "[linear] frequency_hz = 1e+09: drive frequency 1e+09 Hz is outside the "
                                    "generator's range"),
    ({"resonance_search__stop_hz": 800.0}, "[resonance_search] stop_hz = 800"),
    ({"validation__frequency_factor": 30.0}, "[validation #1] frequency_factor (30 x [resonance_search] stop_hz "
                                             "25 Hz) = 750"),
    ({"nonlinear__frequency_hz": 501.0}, "[nonlinear] frequency_hz = 501"),
])
def test_issue15_2_every_drive_frequency_the_protocol_can_produce_is_bounded(tmp_path, changes, needle):
    path = protocol_file(tmp_path, **changes)
    protocol = parse_protocol(tomllib.loads(path.read_text()), path.read_text(), "p.toml")
    with pytest.raises(UserFacingError) as info:
        protocol.check_against_limits(load_config().limits)
    assert needle in str(info.value)


def test_issue15_2_the_frequency_bound_follows_the_sample_rate_and_cannot_exceed_it():
    text = DEFAULT_RIG_PATH.read_text()
    assert load_config().limits["max_drive_frequency_hz"] == 500.0
    assert parse_config(tomllib.loads(text.replace("sample_rate_hz = 10000.0", "sample_rate_hz = 2000.0"))
                        ).limits["max_drive_frequency_hz"] == 100.0
    with pytest.raises(UserFacingError, match=r"\[limits\] max_drive_frequency_hz: 600 Hz exceeds "
                                              r"\[acquisition\] sample_rate_hz / 20 = 500 Hz"):
        parse_config(tomllib.loads(text.replace("[limits]", "[limits]\nmax_drive_frequency_hz = 600.0")))


def test_issue15_2_the_runner_refuses_a_frequency_outside_the_bounds():
    sup = Supervisor(load_config().limits)
    sup.check_frequency(500.0)
    for hz in (500.01, 6000.0, 1e9, 0.0):
        with pytest.raises(LimitError):
            sup.check_frequency(hz)


# ---- item 3 is in test_rig_acquisition.test_instrument_killed_mid_stage (the final message) ------------

# ---- item 4: durations bounded by limits.max_step_duration_s -------------------------------------------

def test_issue15_4_an_absurd_duration_exits_2_naming_the_field(tmp_path, capsys):
    status, err, out = acquire_cli(tmp_path, capsys, protocol_file(tmp_path, validation__duration_s=1e12))
    assert status == 2
    assert "[validation #1] duration_s = 1e+12: step duration 1e+12 s exceeds limits.max_step_duration_s = 3600 s" in err
    assert not out.exists()


@pytest.mark.parametrize("key", ["run__settle_s", "linear__duration_s", "resonance_search__measure_s",
                                 "nonlinear__hold_s"])
def test_issue15_4_every_duration_is_bounded(tmp_path, key):
    path = protocol_file(tmp_path, **{key: 3601.0})
    protocol = parse_protocol(tomllib.loads(path.read_text()), "", "p.toml")
    table, field = key.split("__")
    with pytest.raises(UserFacingError, match=rf"\[{table}\] {field} = 3601: step duration"):
        protocol.check_against_limits(load_config().limits)
    config = parse_config(tomllib.loads(DEFAULT_RIG_PATH.read_text().replace("max_step_duration_s = 3600.0",
                                                                             "max_step_duration_s = 7200.0")))
    protocol.check_against_limits(config.limits)  # a rig config may allow longer steps


def test_shipped_protocol_and_rig_config_pass_the_new_bounds():
    load_protocol().check_against_limits(load_config().limits)  # raises if refused
