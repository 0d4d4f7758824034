"""Line-oriented instrument servers on a real TCP socket (loopback) and, optionally, a pty.

A simulated instrument is a ``handler(line: str) -> str | None`` (None = no reply).
:class:`LineServer` serves it: requests end with CR or LF (either works, empty
lines are ignored), replies are sent with the instrument's terminator.

Bytes that are not ASCII reach the handler as U+FFFD (decoded with replacement;
:func:`is_printable_ascii` tells the handler to answer with its protocol's error),
and a reply is always sent as ASCII. A request line longer than
:data:`MAX_LINE` bytes (an instrument's input buffer) is answered with the
instrument's ``line_too_long`` reply and the connection is dropped (a pty's
input is discarded).

Fault injection for tests, one shot each (:meth:`LineServer.inject`):
``"garbage"`` the next reply is replaced by non-protocol bytes; ``"split"`` the
next reply is sent in 1-byte packets with small pauses; ``"silent"`` the next
request gets no reply; ``"kill"`` the server dies (listening socket, every
connection and the pty closed) on receiving the next request, without replying.
"""
from __future__ import annotations

import os
import select
import socket
import threading
import time
import tty

FAULTS = ("garbage", "split", "silent", "kill")
MAX_LINE = 4096  # bytes of one request line, like an instrument's input buffer


class LineTooLong(Exception):
    """A request line exceeded MAX_LINE bytes."""


def is_printable_ascii(text: str, tab: bool = True) -> bool:
    """True when every character is printable ASCII (or a tab, unless ``tab`` is False: a request
    may hold tabs as whitespace, a reply that echoes part of it may not)."""
    return all(" " <= c <= "~" or (tab and c == "\t") for c in text)


class LineServer:
    def __init__(self, name: str, handler, terminator: str, host: str = "127.0.0.1",
                 port: int = 0, pty: bool = False, line_too_long: str = "line too long"):
        self.name = name
        self.handler = handler
        self.terminator = terminator.encode()
        self.line_too_long = line_too_long
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._sock.bind((host, port))
        except OSError as exc:
            self._sock.close()
            raise OSError(exc.errno, f"{name}: cannot listen on {host}:{port}: {exc.strerror}") from None
        self._sock.listen(8)
        self.host, self.port = self._sock.getsockname()[:2]
        self._clients: set[socket.socket] = set()
        self._faults: list[str] = []
        self._lock = threading.Lock()
        self._handler_lock = threading.Lock()  # one request at a time, like a real instrument
        self.alive = True
        self.on_kill = None  # callable run when the server is killed
        self.pty_path: str | None = None
        self._pty_master: int | None = None
        self._pty_slave: int | None = None
        if pty:
            master, slave = os.openpty()
            tty.setraw(slave)
            self._pty_master, self._pty_slave = master, slave
            self.pty_path = os.ttyname(slave)
        self._threads: list[threading.Thread] = []

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    @property
    def url(self) -> str:
        return f"socket://{self.host}:{self.port}"

    def start(self) -> "LineServer":
        t = threading.Thread(target=self._accept_loop, name=f"{self.name}-accept", daemon=True)
        t.start()
        self._threads.append(t)
        if self._pty_master is not None:
            t = threading.Thread(target=self._pty_loop, name=f"{self.name}-pty", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def inject(self, fault: str) -> None:
        if fault not in FAULTS:
            raise ValueError(f"unknown fault {fault!r}; one of {FAULTS}")
        with self._lock:
            self._faults.append(fault)

    # ---- serving ----------------------------------------------------------------------
    def _accept_loop(self) -> None:
        while self.alive:
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                if not self.alive:
                    conn.close()
                    return
                self._clients.add(conn)
            t = threading.Thread(target=self._client_loop, args=(conn,), name=f"{self.name}-conn",
                                 daemon=True)
            t.start()

    def _client_loop(self, conn: socket.socket) -> None:
        buf = b""
        try:
            while self.alive:
                data = conn.recv(65536)
                if not data:
                    break
                buf += data
                buf = self._process(buf, lambda b: conn.sendall(b))
        except LineTooLong:
            pass  # answered; the connection is dropped
        except OSError:
            pass
        finally:
            with self._lock:
                self._clients.discard(conn)
            try:
                conn.close()
            except OSError:
                pass

    def _pty_loop(self) -> None:
        fd = self._pty_master
        buf = b""

        def send(b: bytes) -> None:
            view = memoryview(b)
            while view:
                n = os.write(fd, view)
                view = view[n:]

        while self.alive:
            try:
                ready, _, _ = select.select([fd], [], [], 0.1)
                if not ready:
                    continue
                data = os.read(fd, 65536)
            except OSError:
                return
            if not data:
                return
            try:
                buf = self._process(buf + data, send)
            except LineTooLong:
                buf = b""  # answered; the rest of the line is discarded
            except OSError:
                return

    def _process(self, buf: bytes, send) -> bytes:
        while True:
            cut = [i for i in (buf.find(b"\r"), buf.find(b"\n")) if i >= 0]
            if not cut or min(cut) > MAX_LINE:
                if len(buf) > MAX_LINE:
                    send(self.line_too_long.encode("ascii") + self.terminator)
                    raise LineTooLong()
                return buf
            i = min(cut)
            line, buf = buf[:i], buf[i + 1:]
            text = line.decode("ascii", errors="replace").strip()
            if not text:
                continue
            fault = None
            with self._lock:
                if self._faults:
                    fault = self._faults.pop(0)
            if fault == "kill":
                self.kill()
                return b""
            with self._handler_lock:
                reply = self.handler(text)
            if reply is None or fault == "silent":
                continue
            out = reply.encode("ascii", errors="replace") + self.terminator
            if fault == "garbage":
                send(b"\x00\xff#!garbage\xfe" + self.terminator)
            elif fault == "split":
                for k in range(len(out)):
                    send(out[k:k + 1])
                    time.sleep(0.002)
            else:
                send(out)

    def drop_connections(self) -> None:
        """Close every open connection but keep listening (a network glitch)."""
        with self._lock:
            clients = list(self._clients)
            self._clients.clear()
        for s in clients:
            try:
                s.shutdown(socket.SHUT_RDWR)
                s.close()
            except OSError:
                pass

    def kill(self) -> None:
        """Abruptly close everything (listening socket, connections, pty)."""
        with self._lock:
            if not self.alive:
                return
            self.alive = False
            clients = list(self._clients)
            self._clients.clear()
        # the instrument is off before its connections drop (as the amplifier's kill mutes first): a
        # client that sees the link die never sees the dead instrument's output still on
        if self.on_kill is not None:
            self.on_kill()
        for s in [self._sock, *clients]:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            try:
                s.close()
            except OSError:
                pass
        for fd in (self._pty_master, self._pty_slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._pty_master = self._pty_slave = None

    def stop(self) -> None:
        self.kill()
