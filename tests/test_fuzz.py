"""Property-based tests (Hypothesis): the TOML loaders and the simulated servers' line parsers take
any input without a traceback (only UserFacingError / the protocol's own error replies) and without
hanging; a model JSON loads or is refused naming the file, and no file is changed; and a protocol the rig
accepts never yields a setpoint beyond the rig's limits.

Bounded: a few hundred examples in all, socket/pty reads time out after 2 s (a hang fails)."""
import json
import math
import os
import re
import select
import socket
import tomllib
import tty

import pytest
from hypothesis import HealthCheck, event, example, given, settings
from hypothesis import strategies as st

from rig.config import DEFAULT_RIG_PATH, load_config, parse_config
from rig.messages import Acquire, CheckSetpoint, Ramp, Rest, SetFrequency
from rig.plans import PlanContext, protocol_plan
from rig.protocol import DEFAULT_PROTOCOL_PATH, load_protocol, parse_protocol
from rig.safety import Supervisor
from shakerlab.errors import UserFacingError
from sim_backend.config import load_config as load_sim_config
from sim_backend.rig import SimulatedRig

from test_rig_plans import FakeSpecimen, run_plan

FAST = settings(max_examples=60, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                        HealthCheck.too_slow])
SCALARS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**12, 10**12), st.booleans(),
                    st.text(max_size=12), st.none())
VALUES = st.recursive(SCALARS, lambda inner: st.one_of(st.lists(inner, max_size=3),
                                                       st.dictionaries(st.text(max_size=8), inner, max_size=3)),
                      max_leaves=6)


def mutated(base: dict, data) -> dict:
    """``base`` with a few fields replaced, removed or added (any TOML-like value)."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    for _ in range(data.draw(st.integers(1, 4))):
        table = data.draw(st.sampled_from(sorted(out) + ["bogus"]))
        action = data.draw(st.sampled_from(["set", "delete", "replace_table"]))
        if action == "replace_table" or not isinstance(out.get(table), dict):
            out[table] = data.draw(VALUES)
            continue
        keys = sorted(out[table]) + [data.draw(st.text(max_size=8))]
        key = data.draw(st.sampled_from(keys))
        if action == "delete":
            out[table].pop(key, None)
        else:
            out[table][key] = data.draw(VALUES)
    return out


def accepted_or_user_error(load):
    try:
        return load()
    except UserFacingError as exc:
        assert str(exc)  # a message, never empty
        return None


# ---- TOML loaders ------------------------------------------------------------------------------------

@FAST
@given(data=st.data())
def test_protocol_loader_accepts_or_names_the_problem(data):
    proto = accepted_or_user_error(lambda: parse_protocol(mutated(tomllib.loads(DEFAULT_PROTOCOL_PATH.read_text()),
                                                                  data), "", "fuzz.toml"))
    if proto is not None:
        accepted_or_user_error(lambda: proto.check_against_limits(load_config().limits))


@FAST
@given(data=st.data())
def test_rig_config_loader_accepts_or_names_the_problem(data):
    accepted_or_user_error(lambda: parse_config(mutated(tomllib.loads(DEFAULT_RIG_PATH.read_text()), data)))


@FAST
@given(data=st.data())
def test_simulator_config_loader_accepts_or_names_the_problem(data):
    base = {"clock": {"sample_rate": 10000.0}, "specimen": {"mass": 0.15, "fn_m": {"y^2": 2.0e5}},
            "effects": {"contact_gap": 0.0}}
    accepted_or_user_error(lambda: load_sim_config(mutated(base, data)))


@settings(max_examples=40, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=st.one_of(st.text(max_size=300), st.binary(max_size=200).map(lambda b: b.decode("latin-1"))))
def test_toml_files_of_any_text_are_refused_cleanly(tmp_path_factory, text):
    path = tmp_path_factory.mktemp("fuzz") / "any.toml"
    path.write_text(text, encoding="utf-8", errors="surrogateescape")
    accepted_or_user_error(lambda: load_protocol(path))
    accepted_or_user_error(lambda: load_config(path))
    accepted_or_user_error(lambda: load_sim_config(path))


# ---- a protocol the rig accepts never drives beyond its limits ----------------------------------------

class ShortWindows(FakeSpecimen):
    def window(self, vpp, hz, duration_s):
        return super().window(vpp, hz, min(duration_s, 0.5))


@settings(max_examples=100, deadline=None, database=None)
@given(amp=st.floats(0.01, 7), hz=st.floats(0.5, 600), factor=st.floats(0.1, 6), fraction=st.floats(0.05, 3),
       start_hz=st.floats(1, 40), span=st.floats(1.1, 5), max_vpp=st.floats(0.05, 7),
       seconds=st.sampled_from([0.2, 1.0, 1.0, 1.0, 5000.0]), relative=st.booleans())
def test_an_accepted_protocol_never_yields_a_setpoint_beyond_the_limits(amp, hz, factor, fraction, start_hz, span,
                                                                        max_vpp, seconds, relative):
    text = f"""
[run]
settle_s = 0.1
[linear]
frequency_hz = {hz!r}
amplitude_vpp = {amp!r}
duration_s = {seconds!r}
[resonance_search]
start_hz = {start_hz!r}
stop_hz = {start_hz * span!r}
steps = 4
refine_steps = 2
amplitude_vpp = {amp / 4!r}
measure_s = 0.2
settle_s = 0.1
[nonlinear]
{"frequency_factor" if relative else "frequency_hz"} = {factor if relative else hz!r}
start_vpp = {min(0.1, max_vpp)!r}
max_vpp = {max_vpp!r}
dwell_s = 0.3
analysis_s = 0.2
hold_s = 0.1
[[validation]]
frequency_factor = {factor!r}
amplitude_fraction = {fraction!r}
duration_s = 0.2
"""
    limits = load_config().limits
    proto = accepted_or_user_error(lambda: parse_protocol(tomllib.loads(text), text, "fuzz.toml"))
    if proto is None:
        return
    try:
        proto.check_against_limits(limits)
    except UserFacingError:
        event("refused by the protocol check")
        return
    event("accepted: plan run")
    sup = Supervisor(limits)
    messages, _ = run_plan(protocol_plan(proto, limits, PlanContext(limits)), ShortWindows(thd_per_vpp2=0.0))
    for msg in messages:  # each raises LimitError if the protocol check let it through
        if isinstance(msg, Ramp):
            sup.check_amplitude(msg.vpp)
        elif isinstance(msg, SetFrequency):
            sup.check_frequency(msg.hz)
        elif isinstance(msg, (Acquire, Rest)):
            sup.check_duration(msg.duration_s)
        elif isinstance(msg, CheckSetpoint):
            sup.check_amplitude(msg.vpp)
            sup.check_frequency(msg.hz)


# ---- the simulated servers' line parsers, over a real socket and a real pty ------------------------------

SCPI_HEADERS = ["*IDN", "*RST", "*CLS", "*OPC", "*TRG", "SYST:ERR", "FREQ", "SOUR1:FREQ", "VOLT", "VOLT:OFFS",
                "VOLT:LIM:HIGH", "VOLT:LIM:LOW", "VOLT:LIM:STAT", "OUTP", "FUNC", "SWE:STAT", "SWE:TIME",
                "BURS:NCYC", "BURS:STAT", "TRIG:SOUR", ":FREQ:STAR", "BOGUS"]
SCPI_ARGS = st.one_of(st.just(""), st.sampled_from(["ON", "OFF", "MIN", "MAX", "DEF", "1e400", "-0", "nan",
                                                    "10KHZ", "5 MV", "1e-9"]),
                      st.floats(allow_nan=False).map(repr), st.text("0123456789.eE+-KHZMVS ", max_size=10))
SCPI_COMMAND = st.builds(lambda h, q, a: f"{h}{'?' if q else ''}{' ' + a if a else ''}",
                         st.sampled_from(SCPI_HEADERS), st.booleans(), SCPI_ARGS)
SCPI_LINES = st.one_of(st.lists(SCPI_COMMAND, min_size=1, max_size=4).map(lambda c: ";".join(c).encode()),
                       st.binary(max_size=120), st.text(max_size=80).map(lambda t: t.encode("utf-8")))
SENSOR_COMMANDS = ["ID", "RG", "SS", "M0", "AS", "AQ", "AO", "ST", "EQ", "XX"]
SENSOR_ARGS = st.one_of(st.sampled_from(["", "0", "1", "10000", "100000", "100001", "-1", "1e3", "x"]),
                        st.text("0123456789,", max_size=8))
SENSOR_LINES = st.one_of(st.builds(lambda c, a: f"{c},{a}" if a else c, st.sampled_from(SENSOR_COMMANDS),
                                   SENSOR_ARGS).map(str.encode),
                         st.binary(max_size=80))
ERROR_ENTRY = re.compile(rb'^[+-]\d+,"[\t -~]*"$')  # printable ASCII (tabs allowed, as the driver does)


# ---- model JSON (recon.model, recon.diagnosis.augmented) -------------------------------------------------

MODEL_BASE = {"kind": "shakerlab.recon.HystereticModel", "excitation": "base",
              "parameters": {"c_m": 1.5, "k_m": 900.0, "alpha_m": 300.0, "gamma": 40.0, "delta": 20.0,
                             "fn_m": {"y^3": 2e7, "y^2*dy": -5.0}}}


@FAST
@given(data=st.data())
def test_model_json_loads_or_names_the_field_and_changes_no_file(tmp_path_factory, data):
    """Any mutation of a model JSON (values of any type, NaN, missing or extra fields, bad terms): the
    loaders accept it or raise UserFacingError naming the file; the file is never changed, and saving
    over it without overwrite, or over a run file even with it, is refused."""
    from recon.diagnosis.augmented import AugmentedModel
    from recon.model import HystereticModel

    d = tmp_path_factory.mktemp("model")
    doc = {k: (dict(v) if isinstance(v, dict) else v) for k, v in MODEL_BASE.items()}
    doc["parameters"] = mutated({"p": dict(MODEL_BASE["parameters"])}, data)["p"] \
        if data.draw(st.booleans()) else doc["parameters"]
    doc = mutated(doc, data) if data.draw(st.booleans()) else doc
    if data.draw(st.booleans()):
        doc = {"kind": "shakerlab.recon.AugmentedModel", "baseline": doc,
               "extras": data.draw(st.dictionaries(st.sampled_from(["mu", "c2", "bogus"]), VALUES, max_size=2))}
    text = json.dumps(doc, allow_nan=True, default=str)
    path = d / "m.json"
    path.write_text(text)
    for loader in (HystereticModel.load, AugmentedModel.load):
        try:
            model = loader(path)
        except UserFacingError as exc:
            event("refused")
            assert str(path) in str(exc)
            continue
        event("accepted")
        params = model.to_dict()["parameters"] if isinstance(model, HystereticModel) else \
            model.baseline.to_dict()["parameters"]
        assert all(math.isfinite(v) for k, v in params.items() if k != "fn_m" and v is not None)
        with pytest.raises(UserFacingError, match="file exists"):
            model.save(path)
        run = d / "run.h5"
        run.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 64)
        with pytest.raises(UserFacingError, match="never overwritten"):
            model.save(run, overwrite=True)
        assert run.read_bytes() == b"\x89HDF\r\n\x1a\n" + b"\0" * 64
    assert path.read_text() == text


@pytest.fixture(scope="module")
def sim():
    rig = SimulatedRig(speed=None, seed=0, pty=True).start()
    yield rig
    rig.stop()


def read_line(read, terminator: bytes) -> bytes:
    out = b""
    while not out.endswith(terminator):
        chunk = read()
        assert chunk, "the server closed the connection"
        out += chunk
    return out


@pytest.mark.slow
@settings(max_examples=80, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(line=SCPI_LINES)
@example(line=b"VOLT:OFFS? 10000000.0;*CLS;*IDN?;SOUR1:FREQ")   # an *IDN? in the line: two identity replies
def test_scpi_server_answers_any_line_and_keeps_serving(sim, line):
    host, port = sim.addresses["generator"].removeprefix("socket://").split(":")
    with socket.create_connection((host, int(port)), timeout=2) as conn:
        conn.sendall(line + b"\n*IDN?\n")
        buf = b""
        while b"shakerlab,SIM33521B" not in buf:  # replies to the fuzzed line come first
            chunk = conn.recv(65536)
            assert chunk, "the server closed the connection"
            buf += chunk
        # the fuzzed line may hold an *IDN? of its own, answered first: then read on until the
        # server is quiet (ours is the last command, so nothing else can follow)
        if b"IDN" in line.upper():
            conn.settimeout(0.5)
            try:
                while chunk := conn.recv(65536):
                    buf += chunk
            except socket.timeout:
                pass
        conn.settimeout(2)
        for _ in range(25):  # every queued error is readable ASCII, and the queue empties
            conn.sendall(b"SYST:ERR?\n")
            entry = read_line(lambda: conn.recv(1), b"\n")[:-1]
            assert ERROR_ENTRY.match(entry), entry
            if entry.startswith(b"+0,"):
                break
        else:
            pytest.fail("the error queue does not empty")
        conn.sendall(b"*RST;*CLS\n")


@settings(max_examples=80, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(line=SENSOR_LINES)
@example(line=b"!\t!")     # a tab inside an unknown command was echoed into the error reply (CI, 2026-11-28h)
def test_sensor_server_answers_any_line_over_a_pty(sim, line):
    fd = os.open(sim.pty_paths["sensor_base"], os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)

    def read():
        ready, _, _ = select.select([fd], [], [], 2.0)
        assert ready, "no reply within 2 s"
        return os.read(fd, 65536)

    try:
        os.write(fd, line.replace(b"\n", b"").replace(b"\r", b"") + b"\rID\r")
        buf = b""
        while b"ID,shakerlab SIM-LKG5001,base\r" not in buf:
            buf += read()
        for reply in buf.split(b"\r")[:-1]:
            assert re.fullmatch(rb"[ -~]*", reply), reply  # printable ASCII only
    finally:
        os.write(fd, b"AQ\r")
        read_line(read, b"\r")
        os.close(fd)
