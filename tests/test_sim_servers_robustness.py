"""Issue 15, items 18-20: the simulated servers survive any bytes (non-ASCII, control bytes,
endless lines) and answer with their protocol's error; messages name the instrument, the port
and what is wrong with an address. Real sockets and ptys."""
import os
import socket
import time
import tty

import pytest

from drivers.base import InstrumentFault
from drivers.signal_generator import SignalGenerator
from rig.config import load_config
from rig.protocol import load_protocol
from rig.session import acquire
from shakerlab.cli import main
from shakerlab.errors import UserFacingError
from sim_backend.line_server import MAX_LINE
from sim_backend.rig import SimulatedRig


@pytest.fixture(scope="module")
def sim():
    rig = SimulatedRig(speed=None, seed=0, pty=True).start()
    yield rig
    rig.stop()


def connect(sim, name):
    host, port = sim.addresses[name].removeprefix("socket://").split(":")
    conn = socket.create_connection((host, int(port)), timeout=3)
    return conn, conn.makefile("rb")


def ask(conn, reader, request: bytes) -> bytes:
    conn.sendall(request)
    return reader.readline()


def read_until_cr(conn) -> bytes:
    out = b""
    while not out.endswith(b"\r"):
        chunk = conn.recv(1)
        if not chunk:
            break
        out += chunk
    return out


# ---- item 18: one non-ASCII byte ------------------------------------------------------------------

@pytest.mark.parametrize("bad", [b"\xff\n", b"*IDN?\xff\n", b"\x00FREQ 10\n", b"\xc3\xa9\n"])
def test_issue15_18_non_ascii_byte_gets_a_scpi_error_and_the_connection_lives(sim, bad):
    conn, reader = connect(sim, "generator")
    with conn:
        conn.sendall(bad)
        assert ask(conn, reader, b"SYST:ERR?\n") == b'-101,"Invalid character; a non-ASCII or control byte in the request"\n'
        assert ask(conn, reader, b"*IDN?\n").startswith(b"shakerlab,SIM33521B")   # same connection still served
    other, other_reader = connect(sim, "generator")
    with other:
        assert ask(other, other_reader, b"SYST:ERR?\n") == b'+0,"No error"\n'  # no poisoned queue for others
    with SignalGenerator(sim.addresses["generator"]) as gen:
        gen.frequency = 12.5
        assert gen.frequency == 12.5 and gen.check_errors() == []


def test_issue15_18_non_ascii_byte_to_a_sensor_is_an_error_reply(sim):
    conn, _ = connect(sim, "sensor_base")
    with conn:
        conn.sendall(b"\xffID\r")
        assert read_until_cr(conn) == b"ER,??,00\r"
        conn.sendall(b"ID\r")
        assert read_until_cr(conn) == b"ID,shakerlab SIM-LKG5001,base\r"


# ---- item 19: line length capped ----------------------------------------------------------------------

@pytest.mark.parametrize("name,reply", [("generator", b'-223,"Too much data; request line longer than 4096 '
                                                      b'bytes: connection closed"\n'),
                                        ("sensor_tip", b"ER,??,20\r")])
def test_issue15_19_an_endless_line_is_answered_and_the_connection_dropped(sim, name, reply):
    conn, _ = connect(sim, name)
    sent, refused = 0, False
    with conn:
        try:
            while sent < 50_000_000:
                conn.sendall(b"A" * 65536)
                sent += 65536
        except OSError:
            refused = True   # the server closed the connection while we were still sending
        received = b""
        try:
            while chunk := conn.recv(4096):
                received += chunk
        except OSError:
            pass
    assert refused, f"the server took {sent} bytes of one line"
    assert sent < 20_000_000
    assert received in (reply, b"")  # the reply may be lost to the reset; the connection is gone either way
    fresh, reader = connect(sim, name)  # the server still serves others
    with fresh:
        request, head = (b"*IDN?\n", b"shakerlab") if name == "generator" else (b"ID\r", b"ID,")
        fresh.sendall(request)
        assert (reader.readline() if name == "generator" else read_until_cr(fresh)).startswith(head)


def test_issue15_19_a_line_just_under_the_cap_is_still_served(sim):
    conn, reader = connect(sim, "generator")
    with conn:
        line = b"*IDN?;" + b" " * (MAX_LINE - 20) + b"\n"
        assert ask(conn, reader, line).startswith(b"shakerlab")


def test_issue15_19_an_endless_line_over_a_pty_is_answered_and_discarded(sim):
    fd = os.open(sim.pty_paths["generator"], os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    try:
        os.write(fd, b"B" * (MAX_LINE + 100))
        deadline, got = time.monotonic() + 3, b""
        while not got.endswith(b"\n") and time.monotonic() < deadline:
            got += os.read(fd, 4096)
        assert got.startswith(b'-223,"Too much data')
        os.write(fd, b"\n*IDN?\n")
        got = b""
        while not got.endswith(b"\n") and time.monotonic() < deadline:
            got += os.read(fd, 4096)
        assert got.startswith(b"shakerlab")
    finally:
        os.close(fd)


# ---- item 20: messages ---------------------------------------------------------------------------------

def test_issue15_20_port_in_use_names_the_instrument_and_the_port(capsys):
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        for option, name in (("--sensor-tip-port", "sensor_tip"), ("--amplifier-port", "amplifier")):
            status = main(["sim", "serve", "--duration", "0.1", option, str(port)])
            err = capsys.readouterr().err
            assert status == 2
            assert f"{name}: cannot listen on 127.0.0.1:{port}" in err and "Traceback" not in err


@pytest.mark.parametrize("url,needle", [
    ("socket://nohost:x", "bad address 'socket://nohost:x': expected socket://host:port with a port 1..65535"),
    ("sockt://127.0.0.1:5030", "unknown URL scheme 'sockt://'"),
])
def test_issue15_20_a_bad_sensor_url_is_named_clearly(tmp_path, sim, url, needle):
    config = load_config().with_addresses({**sim.addresses, "sensor_tip": url})
    with pytest.raises(UserFacingError) as info:
        acquire(config, load_protocol(), tmp_path / "r.h5", lockstep=True)
    assert "laser sensor tip: connect" in str(info.value) and needle in str(info.value)
    assert "debug|info" not in str(info.value) and not (tmp_path / "r.h5").exists()


def test_issue15_20_sensor_errors_say_base_or_tip(sim):
    from rig.instruments import RigInstruments

    inst = RigInstruments(load_config().with_addresses(sim.addresses), lockstep=True)
    inst.connect()
    try:
        with pytest.raises(InstrumentFault, match=r"^laser sensor tip: AO,5: error 30"):
            inst.tip.fetch(5)  # not armed
        with pytest.raises(InstrumentFault, match=r"^laser sensor base: AO,5: error 30"):
            inst.base.fetch(5)
    finally:
        inst.close()
