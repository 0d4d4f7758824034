"""A line-based request/reply link over a VISA resource (pyvisa).

The same calls as :class:`drivers.line_link.LineLink` (``query``, ``write``,
``close``), so a text-protocol driver takes either.  Resource strings are
VISA's: ``TCPIP0::192.168.1.20::5025::SOCKET`` (raw socket), ``TCPIP0::host::inst0::INSTR``
(VXI-11), ``USB0::0x0957::0x2C07::MY1234::INSTR`` (USBTMC), ``GPIB0::10::INSTR``,
``ASRL/dev/ttyUSB0::INSTR`` (serial; the :class:`~drivers.line_link.SerialSettings` apply).

The VISA library: ``""`` picks NI-VISA / Keysight IO Libraries when one is
installed and pyvisa-py (pure Python: TCPIP, and USB/GPIB/serial with their
optional packages) otherwise; ``"@py"`` forces pyvisa-py, ``"@ivi"`` the
vendor library.  Errors and the reconnect policy are those of ``LineLink``:
after a transport error or timeout the session is closed and the next call
reopens it; a failed command is never re-sent.
"""
from __future__ import annotations

import re
import time

import pyvisa
import pyvisa.constants as vc

from drivers.base import InstrumentConnectionError, InstrumentTimeout, MalformedReply
from drivers.line_link import LineTransport, SerialSettings

RESOURCE = re.compile(r"^(TCPIP|USB|GPIB|ASRL|VXI|PXI)\d*::", re.IGNORECASE)
VISA_LIBRARIES = ("", "@py", "@ivi")
_PARITY = {"none": vc.Parity.none, "even": vc.Parity.even, "odd": vc.Parity.odd, "mark": vc.Parity.mark,
           "space": vc.Parity.space}
_STOP = {1: vc.StopBits.one, 1.5: vc.StopBits.one_and_a_half, 2: vc.StopBits.two}
_FLOW = {"none": vc.ControlFlow.none, "xonxoff": vc.ControlFlow.xon_xoff, "rtscts": vc.ControlFlow.rts_cts,
         "dsrdtr": vc.ControlFlow.dtr_dsr}


def is_visa_resource(address: str) -> bool:
    """True for a VISA resource string (``TCPIP0::...``, ``USB0::...``, ``GPIB0::...``, ``ASRL...``)."""
    return isinstance(address, str) and RESOURCE.match(address.strip()) is not None


class VisaLink(LineTransport):
    def __init__(self, instrument: str, resource: str, timeout: float = 1.0, write_term: str = "\n",
                 read_term: str = "\n", serial_settings: SerialSettings | None = None, visa_library: str = "",
                 reconnect_attempts: int = 3, reconnect_delay: float = 0.1):
        super().__init__(instrument, timeout, write_term, read_term)
        if not is_visa_resource(resource):
            raise ValueError(f"{instrument}: {resource!r} is not a VISA resource string "
                             f"(TCPIP0::host::port::SOCKET, TCPIP0::host::inst0::INSTR, USB0::...::INSTR, "
                             f"GPIB0::10::INSTR, ASRL/dev/ttyUSB0::INSTR)")
        if visa_library not in VISA_LIBRARIES:
            raise ValueError(f"{instrument}: VISA library {visa_library!r} is not one of "
                             f"{', '.join(map(repr, VISA_LIBRARIES))}")
        self.url = resource.strip()
        self.write_term = write_term
        self.read_term = read_term
        self.serial_settings = SerialSettings() if serial_settings is None else serial_settings
        self.visa_library = visa_library
        self.reconnect_attempts = reconnect_attempts
        self.reconnect_delay = reconnect_delay
        self._rm = None
        self._session = None
        self.open()

    # ---- connection -----------------------------------------------------------------------
    def open(self) -> None:
        last = None
        for attempt in range(max(1, self.reconnect_attempts)):
            try:
                if self._rm is None:
                    self._rm = pyvisa.ResourceManager(self.visa_library)
                session = self._rm.open_resource(self.url, open_timeout=int(self.timeout * 1000))
                session.timeout = int(self.timeout * 1000)
                session.read_termination = self.read_term
                session.write_termination = self.write_term
                if self.url.upper().startswith("ASRL"):
                    s = self.serial_settings
                    session.baud_rate = s.baudrate
                    session.data_bits = s.data_bits
                    session.parity = _PARITY[s.parity]
                    session.stop_bits = _STOP[s.stop_bits]
                    session.flow_control = _FLOW[s.flow_control]
                self._session = session
                return
            except (pyvisa.Error, OSError, ValueError) as exc:
                last = exc
                if attempt + 1 < self.reconnect_attempts:
                    time.sleep(self.reconnect_delay)
        raise InstrumentConnectionError(self.instrument, f"connect {self.url}", f"cannot open: {last}")

    def close(self) -> None:
        session, self._session = self._session, None
        if session is not None:
            try:
                session.close()
            except (pyvisa.Error, OSError):
                pass

    def close_library(self) -> None:
        self.close()
        rm, self._rm = self._rm, None
        if rm is not None:
            try:
                rm.close()
            except (pyvisa.Error, OSError):
                pass

    @property
    def is_open(self) -> bool:
        return self._session is not None

    # ---- I/O ----------------------------------------------------------------------------------
    def _send(self, command: str) -> None:
        if self._session is None:
            self.open()
        try:
            self._session.write(command)
        except pyvisa.VisaIOError as exc:
            self.close()
            if exc.error_code == vc.StatusCode.error_timeout:
                raise InstrumentTimeout(self.instrument, command, "write timed out") from None
            raise InstrumentConnectionError(self.instrument, command, f"connection lost while sending: {exc}") from None
        except (pyvisa.Error, OSError) as exc:
            self.close()
            raise InstrumentConnectionError(self.instrument, command, f"connection lost while sending: {exc}") from None

    def _read_line(self, command: str, timeout: float) -> str:
        session = self._session
        try:
            session.timeout = int(timeout * 1000)
            raw = session.read_raw()
        except pyvisa.VisaIOError as exc:
            self.close()
            if exc.error_code == vc.StatusCode.error_timeout:
                raise InstrumentTimeout(self.instrument, command, f"no complete reply within {timeout:g} s") from None
            raise InstrumentConnectionError(self.instrument, command,
                                            f"connection lost while waiting for the reply: {exc}") from None
        except (pyvisa.Error, OSError) as exc:
            self.close()
            raise InstrumentConnectionError(self.instrument, command,
                                            f"connection lost while waiting for the reply: {exc}") from None
        finally:
            if self._session is not None:
                self._session.timeout = int(self.timeout * 1000)
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            self.close()
            raise MalformedReply(self.instrument, command, f"non-ASCII reply {raw[:60]!r}") from None
        text = text.removesuffix(self.read_term)
        if any(ord(c) < 32 and c not in "\t" for c in text.strip("\r\n")):
            self.close()
            raise MalformedReply(self.instrument, command, f"control characters in reply {raw[:60]!r}")
        return text.strip("\r\n")
