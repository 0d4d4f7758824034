"""A line-based request/reply link over pyserial (``socket://``, real serial ports, ptys).

The serial line settings (:class:`SerialSettings`: baud rate, data bits,
parity, stop bits, flow control) are the instrument's, as set on its front
panel; they matter on a serial device or pty and are ignored by a socket.

Every call has a deadline; a missing, partial or undecodable reply raises an
:class:`~drivers.base.InstrumentError` subclass naming the instrument and the
command, never hangs.  Reconnect policy: after any transport error or timeout
the link is closed (so a late reply cannot be mistaken for the next one) and
the next call reopens it, trying ``reconnect_attempts`` times with
``reconnect_delay`` between tries.  A failed command is never re-sent
automatically (a trigger or a buffer fetch must not happen twice).
"""
from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass

import serial

from drivers.base import InstrumentConnectionError, InstrumentTimeout, MalformedReply

MAX_REPLY = 16 * 1024 * 1024
# a reply may hold printable ASCII and tabs; any other control character says the line is garbled
CONTROL_CHARACTERS = re.compile(rb"[\x00-\x08\x0a-\x1f]")
URL_SCHEMES = ("socket", "rfc2217", "loop", "spy", "alt", "hwgrep")  # pyserial's URL handlers
URL_FORMS = "socket://host:port, a serial device such as /dev/ttyUSB0, or a pty path"


BAUD_RATES = (300, 600, 1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
DATA_BITS = {5: serial.FIVEBITS, 6: serial.SIXBITS, 7: serial.SEVENBITS, 8: serial.EIGHTBITS}
PARITIES = {"none": serial.PARITY_NONE, "even": serial.PARITY_EVEN, "odd": serial.PARITY_ODD,
            "mark": serial.PARITY_MARK, "space": serial.PARITY_SPACE}
STOP_BITS = {1: serial.STOPBITS_ONE, 1.5: serial.STOPBITS_ONE_POINT_FIVE, 2: serial.STOPBITS_TWO}
FLOW_CONTROLS = ("none", "xonxoff", "rtscts", "dsrdtr")
TERMINATIONS = ("\n", "\r", "\r\n")


@dataclass(frozen=True)
class SerialSettings:
    """The line settings of a serial instrument; each is checked when made (ValueError names it)."""

    baudrate: int = 115200
    data_bits: int = 8
    parity: str = "none"
    stop_bits: float = 1
    flow_control: str = "none"

    def __post_init__(self):
        checks = (("baudrate", BAUD_RATES), ("data_bits", tuple(DATA_BITS)), ("parity", tuple(PARITIES)),
                  ("stop_bits", tuple(STOP_BITS)), ("flow_control", FLOW_CONTROLS))
        for name, allowed in checks:
            value = getattr(self, name)
            if isinstance(value, bool) or value not in allowed:
                raise ValueError(f"serial {name}: {value!r} is not one of {', '.join(map(str, allowed))}")

    def pyserial_kwargs(self) -> dict:
        """The keyword arguments of ``serial.serial_for_url`` these settings make."""
        return {"baudrate": self.baudrate, "bytesize": DATA_BITS[self.data_bits],
                "parity": PARITIES[self.parity], "stopbits": STOP_BITS[self.stop_bits],
                "xonxoff": self.flow_control == "xonxoff", "rtscts": self.flow_control == "rtscts",
                "dsrdtr": self.flow_control == "dsrdtr"}


def url_problem(url: str) -> str | None:
    """Why ``url`` is not a pyserial URL this link can open (None when it looks right)."""
    if not isinstance(url, str) or not url.strip():
        return f"no address given (expected {URL_FORMS})"
    scheme, sep, rest = url.partition("://")
    if not sep:
        return None  # a device path: the OS says whether it exists
    if scheme not in URL_SCHEMES:
        return f"unknown URL scheme {scheme + '://'!r} in {url!r} (expected {URL_FORMS})"
    if scheme == "socket":
        host, colon, port = rest.split("?", 1)[0].rpartition(":")
        if not colon or not host or not port.isdigit() or not 0 < int(port) < 65536:
            return f"bad address {url!r}: expected socket://host:port with a port 1..65535"
    return None


class LineTransport:
    """What every line-based request/reply link shares: the checked timeout and line terminations,
    and ``write``/``query`` serialised by one lock. A link sends with ``_send`` and reads one reply
    line with ``_read_line``."""

    def __init__(self, instrument: str, timeout: float, write_term: str, read_term: str):
        if not isinstance(timeout, (int, float)) or not timeout > 0:
            raise ValueError(f"{instrument}: timeout must be > 0 s, got {timeout!r}")
        for what, term in (("write", write_term), ("read", read_term)):
            if term not in TERMINATIONS:
                raise ValueError(f"{instrument}: {what} termination {term!r} is not one of "
                                 f"{', '.join(map(repr, TERMINATIONS))}")
        self.instrument = instrument
        self.timeout = float(timeout)
        self._lock = threading.Lock()

    def write(self, command: str) -> None:
        with self._lock:
            self._send(command)

    def query(self, command: str, timeout: float | None = None) -> str:
        with self._lock:
            self._send(command)
            return self._read_line(command, self.timeout if timeout is None else timeout)

    def _send(self, command: str) -> None:
        raise NotImplementedError

    def _read_line(self, command: str, timeout: float) -> str:
        raise NotImplementedError


class LineLink(LineTransport):
    def __init__(self, instrument: str, url: str, timeout: float = 1.0, write_term: str = "\n",
                 read_term: str = "\n", serial_settings: SerialSettings | None = None,
                 reconnect_attempts: int = 3, reconnect_delay: float = 0.1):
        super().__init__(instrument, timeout, write_term, read_term)
        self.url = url
        self.write_term = write_term.encode()
        self.read_term = read_term.encode()
        self.serial_settings = SerialSettings() if serial_settings is None else serial_settings
        self.reconnect_attempts = reconnect_attempts
        self.reconnect_delay = reconnect_delay
        self._port: serial.SerialBase | None = None
        self._buf = bytearray()
        self._lock = threading.Lock()
        self.open()

    # ---- connection -----------------------------------------------------------------------
    def open(self) -> None:
        problem = url_problem(self.url)
        if problem is not None:
            raise InstrumentConnectionError(self.instrument, f"connect {self.url}", problem)
        last = None
        for attempt in range(max(1, self.reconnect_attempts)):
            try:
                self._port = serial.serial_for_url(self.url, timeout=self.timeout, write_timeout=self.timeout,
                                                   **self.serial_settings.pyserial_kwargs())
                self._buf.clear()
                return
            except (serial.SerialException, OSError, ValueError) as exc:
                last = exc
                if attempt + 1 < self.reconnect_attempts:
                    time.sleep(self.reconnect_delay)
        raise InstrumentConnectionError(self.instrument, f"connect {self.url}",
                                        f"cannot open: {last}")

    def close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass

    @property
    def is_open(self) -> bool:
        return self._port is not None

    # ---- I/O ----------------------------------------------------------------------------------
    def _send(self, command: str) -> None:
        if self._port is None:
            self.open()
        try:
            self._port.write(command.encode("ascii") + self.write_term)
            self._port.flush()
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise InstrumentConnectionError(self.instrument, command, f"connection lost while sending: {exc}") from None
        except serial.SerialTimeoutException:
            self.close()
            raise InstrumentTimeout(self.instrument, command, "write timed out") from None

    def _read_line(self, command: str, timeout: float) -> str:
        port = self._port
        deadline = time.monotonic() + timeout
        try:
            while True:
                i = self._buf.find(self.read_term)
                if i >= 0:
                    raw = bytes(self._buf[:i])
                    del self._buf[: i + len(self.read_term)]
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    partial = f" (partial reply {bytes(self._buf[:60])!r})" if self._buf else ""
                    self.close()
                    raise InstrumentTimeout(self.instrument, command,
                                            f"no complete reply within {timeout:g} s{partial}")
                port.timeout = left
                chunk = port.read(1)
                if chunk:
                    port.timeout = 0
                    chunk += port.read(1 << 20)
                    self._buf += chunk
                    if len(self._buf) > MAX_REPLY:
                        self.close()
                        raise MalformedReply(self.instrument, command, "reply exceeds 16 MiB without a terminator")
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise InstrumentConnectionError(self.instrument, command,
                                            f"connection lost while waiting for the reply: {exc}") from None
        finally:
            if self._port is not None:
                self._port.timeout = self.timeout
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            self.close()
            raise MalformedReply(self.instrument, command, f"non-ASCII reply {raw[:60]!r}") from None
        if CONTROL_CHARACTERS.search(raw):
            self.close()
            raise MalformedReply(self.instrument, command, f"control characters in reply {raw[:60]!r}")
        return text.strip("\r\n")
