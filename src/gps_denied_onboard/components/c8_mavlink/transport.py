"""C8 listening transports that answer only the autopilot: pymavlink's ``udpin:`` and ``tcpin:`` with
their client bookkeeping replaced.

pymavlink's ``udpin`` adds the source of every datagram to a set it never shrinks and writes every
message to each member; its ``tcpin`` accepts one connection and reads no other until that one closes.
Here:
- Input: every datagram and every connection is read; each datagram is parsed on its own, each TCP
  client with its own parser (signing state shared). ``source`` is where the message ``recv_msg``
  returned last came from.
- Output: only to the autopilot's source. The link decides when ``follow_source()`` moves it (the
  first valid message of the autopilot's; later only its HEARTBEAT from a new address once the old one
  has been silent past ``mavlink.link_timeout_s``: ``MavlinkLink``); nothing is written before one.
  ``source_is_autopilot()`` and ``source_label()`` tell the link where the last message came from.
- Bounds: UDP keeps one address (``clients``); TCP keeps at most ``TCP_MAX_CLIENTS`` connections and
  closes one that has not sent the autopilot's HEARTBEAT within ``TCP_CLIENT_HELLO_TIMEOUT_S``.
"""

from __future__ import annotations

import contextlib
import errno
import select
import socket
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Final

from gps_denied_onboard.components.c8_mavlink.messages import mavutil

#: Datagrams read per ``recv_msg`` call while none of them holds a message (keeps one call short).
UDP_DATAGRAMS_PER_RECV: Final[int] = 64
#: TCP connections held at once (the autopilot's and ones that have not proven themselves yet); a
#: new one beyond this closes the oldest that is not the autopilot's.
TCP_MAX_CLIENTS: Final[int] = 8
#: A TCP client that has not sent the autopilot's valid HEARTBEAT this long after connecting (or after
#: another connection took the output from it) is closed, s. ArduPilot sends HEARTBEAT at 1 Hz.
TCP_CLIENT_HELLO_TIMEOUT_S: Final[float] = 5.0
#: Bytes read from one TCP client per read.
TCP_READ_BYTES: Final[int] = 4096
#: Bytes waiting for a slow autopilot TCP connection; a whole message that does not fit is dropped.
TCP_OUT_MAX_BYTES: Final[int] = 65536
_NOTHING_WAITING: Final[frozenset[int]] = frozenset({errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED})


def open_transport(url: str, *, baud: int, source_system: int, source_component: int) -> Any:
    """The pymavlink connection for ``url``: ``udpin:``/``udp:`` and ``tcpin:`` as the classes below,
    anything else (one peer only: ``udpout:``, ``tcp:``, serial) as pymavlink makes it."""
    scheme, _, host_port = url.partition(":")
    if scheme in ("udpin", "udp"):
        return AutopilotUdpIn(host_port, source_system=source_system, source_component=source_component)
    if scheme == "tcpin":
        return AutopilotTcpIn(host_port, source_system=source_system, source_component=source_component)
    return mavutil.mavlink_connection(
        url,
        baud=baud,
        source_system=source_system,
        source_component=source_component,
        autoreconnect=False,  # reconnects are the link's: pymavlink's sleep and block
        retries=0,
    )


def _drop_partial_packet(mav: Any) -> None:
    """Forget bytes left after a datagram's last whole packet: a MAVLink datagram holds whole packets,
    so they are never completed by the next datagram (which may come from someone else)."""
    if mav.buf_len():
        mav.buf = bytearray()
        mav.buf_index = 0


class AutopilotUdpIn(mavutil.mavudp):
    """A ``udpin:`` socket that writes only to the autopilot's address (module docstring)."""

    def __init__(self, host_port: str, *, source_system: int, source_component: int) -> None:
        super().__init__(
            host_port, input=True, source_system=source_system, source_component=source_component
        )
        self._inbox: deque[tuple[Any, tuple[str, int]]] = deque()
        #: Sender of the message recv_msg returned last.
        self.source: tuple[str, int] | None = None
        #: Where everything is written (None: nowhere yet); ``clients`` mirrors it for pymavlink's readers.
        self.autopilot_addr: tuple[str, int] | None = None

    def _next_datagram(self) -> tuple[bytes, tuple[str, int]] | None:
        try:
            data, addr = self.port.recvfrom(mavutil.UDP_MAX_PACKET_LEN)
        except OSError as exc:
            if exc.errno in _NOTHING_WAITING:
                return None
            raise
        return data, addr

    def recv(self, n: int | None = None) -> bytes:
        """One datagram's bytes (b"" when none is waiting); unlike pymavlink's, its sender is not kept."""
        got = self._next_datagram()
        return b"" if got is None else got[0]

    def recv_msg(self) -> Any:
        for _ in range(UDP_DATAGRAMS_PER_RECV):
            if self._inbox:
                break
            got = self._next_datagram()
            if got is None:
                break
            data, addr = got
            for msg in self.mav.parse_buffer(data) or ():
                self.post_message(msg)
                self._inbox.append((msg, addr))
            _drop_partial_packet(self.mav)
        if not self._inbox:
            return None
        msg, self.source = self._inbox.popleft()
        return msg

    @property
    def autopilot_known(self) -> bool:
        """True once the output follows an autopilot address."""
        return self.autopilot_addr is not None

    def source_is_autopilot(self) -> bool:
        """Whether the message ``recv_msg`` returned last came from the address the output follows."""
        return self.source is not None and self.source == self.autopilot_addr

    def source_label(self) -> str:
        """Where the message ``recv_msg`` returned last came from, as ``HOST:PORT``."""
        return "?" if self.source is None else f"{self.source[0]}:{self.source[1]}"

    def write(self, buf: bytes) -> None:
        addr = self.autopilot_addr
        if addr is None:
            return
        with contextlib.suppress(OSError):  # as pymavlink: a refused datagram is lost, the next may go
            self.port.sendto(buf, addr)

    def follow_source(self) -> str | None:
        """Write to the sender of the last returned message from now on; returns it as ``HOST:PORT``
        when that changed the address, else None."""
        return None if self.source is None else self.follow(self.source)

    def follow(self, addr: tuple[str, int]) -> str | None:
        """Write to ``addr`` from now on; returns it as ``HOST:PORT`` when that changed the address."""
        if addr == self.autopilot_addr:
            return None
        self.autopilot_addr = addr
        self.clients = {addr}
        return f"{addr[0]}:{addr[1]}"


@dataclass(eq=False)
class _TcpClient:
    sock: socket.socket
    fd: int
    peer: str
    parser: Any
    #: Monotonic time by which it must send the autopilot's HEARTBEAT (None: it is the autopilot's).
    hello_deadline_s: float | None
    out: bytearray = field(default_factory=bytearray)


class AutopilotTcpIn(mavutil.mavtcpin):
    """A ``tcpin:`` listener that accepts several connections and writes only to the autopilot's
    (module docstring). ``fd`` is an epoll descriptor over the listener and every client."""

    def __init__(self, host_port: str, *, source_system: int, source_component: int) -> None:
        super().__init__(host_port, source_system=source_system, source_component=source_component)
        self.listen.listen(TCP_MAX_CLIENTS)
        self._poller = select.epoll()
        self._poller.register(self.listen.fileno(), select.EPOLLIN)
        self.fd = self._poller.fileno()
        self._clients: dict[int, _TcpClient] = {}
        self._autopilot: _TcpClient | None = None
        self._inbox: deque[tuple[Any, _TcpClient]] = deque()
        #: Connection the message recv_msg returned last came from.
        self.source: _TcpClient | None = None

    @property
    def client_count(self) -> int:
        return len(self._clients)

    @property
    def autopilot_known(self) -> bool:
        """True while the output follows an autopilot connection."""
        return self._autopilot is not None

    def source_is_autopilot(self) -> bool:
        """Whether the message ``recv_msg`` returned last came from the connection the output follows."""
        return self.source is not None and self.source is self._autopilot

    def source_label(self) -> str:
        """The peer of the connection the message ``recv_msg`` returned last came from, ``HOST:PORT``."""
        return "?" if self.source is None else self.source.peer

    def recv(self, n: int | None = None) -> bytes:
        return b""  # every read goes through recv_msg (one parser per connection)

    def recv_msg(self) -> Any:
        if not self._inbox:
            now = time.monotonic()
            for client in list(self._clients.values()):
                deadline = client.hello_deadline_s
                if deadline is not None and now >= deadline:
                    self._close(client)
            listen_fd = self.listen.fileno()
            for fd, _events in self._poller.poll(0):
                if fd == listen_fd:
                    self._accept(now)
                elif (readable := self._clients.get(fd)) is not None:
                    self._read(readable)
        if not self._inbox:
            return None
        msg, self.source = self._inbox.popleft()
        return msg

    def _accept(self, now: float) -> None:
        while True:
            try:
                sock, addr = self.listen.accept()
            except OSError:  # nothing waiting (or out of descriptors: it stays in the backlog)
                return
            if len(self._clients) >= TCP_MAX_CLIENTS:
                waiting = [c for c in self._clients.values() if c is not self._autopilot]
                self._close(min(waiting, key=lambda c: c.hello_deadline_s or 0.0))
            sock.setblocking(False)
            sock.setsockopt(socket.SOL_TCP, socket.TCP_NODELAY, 1)
            mavutil.set_close_on_exec(sock.fileno())
            parser = type(self.mav)(None, srcSystem=self.source_system, srcComponent=self.source_component)
            parser.robust_parsing = True
            parser.signing = self.mav.signing  # one signing state: keys, accepted timestamps
            client = _TcpClient(
                sock, sock.fileno(), f"{addr[0]}:{addr[1]}", parser, now + TCP_CLIENT_HELLO_TIMEOUT_S
            )
            self._clients[client.fd] = client
            self._poller.register(client.fd, select.EPOLLIN)

    def _read(self, client: _TcpClient) -> None:
        try:
            data = client.sock.recv(TCP_READ_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._close(client)
            return
        if not data:  # the peer closed
            self._close(client)
            return
        for msg in client.parser.parse_buffer(data) or ():
            self.post_message(msg)
            self._inbox.append((msg, client))

    def _close(self, client: _TcpClient) -> None:
        if self._clients.get(client.fd) is client:
            del self._clients[client.fd]
            self._poller.unregister(client.fd)
        client.sock.close()
        if client is self._autopilot:
            self._autopilot = None

    def write(self, buf: bytes) -> None:
        client = self._autopilot
        if client is None:
            return
        if len(client.out) + len(buf) <= TCP_OUT_MAX_BYTES:
            client.out += buf  # whole messages only, so the stream stays framed
        try:
            sent = client.sock.send(client.out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._close(client)
            return
        del client.out[:sent]

    def follow_source(self) -> str | None:
        """Write to the connection of the last returned message from now on; returns its peer as
        ``HOST:PORT`` when that changed the connection, else None. The previous one gets
        ``TCP_CLIENT_HELLO_TIMEOUT_S`` to send a newer HEARTBEAT before it is closed."""
        client = self.source
        if client is None or client is self._autopilot or self._clients.get(client.fd) is not client:
            return None
        old = self._autopilot
        if old is not None:
            old.hello_deadline_s = time.monotonic() + TCP_CLIENT_HELLO_TIMEOUT_S
            old.out.clear()
        client.hello_deadline_s = None
        self._autopilot = client
        return client.peer

    def close(self) -> None:
        for client in list(self._clients.values()):
            self._close(client)
        self.listen.close()
        self._poller.close()
