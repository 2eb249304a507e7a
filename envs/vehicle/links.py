"""The vehicle's MAVLink links: the ports it opens and the ground stations on them.

:class:`Links` opens one endpoint per connection URL and keeps the links that talk
through them, each with an id (the first element of a :data:`Peer`):

- ``udpout:HOST:PORT``, ``tcp:HOST:PORT``: one pymavlink connection, one link;
- ``udpin:HOST:PORT``: a socket bound there; every address that writes to it is a link
  of its own (:class:`UdpPeer`), like a TCP client: it gets the telemetry and the answers
  to its own requests, so several ground stations may share the port (pymavlink 2.4's
  own ``udpin`` sends every message to every address that wrote: each ground station
  also got the others' mission requests and acknowledgements, and one MAVLink 1
  ground station made the whole port MAVLink 1). An address silent for
  :data:`UDP_PEER_TIMEOUT_S` is forgotten, except the last one that wrote (a script
  that sent once and only listens keeps its telemetry);
- ``tcpin:HOST:PORT``: a listening socket that accepts every ground station that
  connects; each client is a link of its own, with its own parser and encoder, so each
  gets the telemetry and the answers to its own requests. Sockets never block the
  vehicle: what a client does not read waits in a bounded buffer
  (:data:`TCP_BUFFER_BYTES`; whole messages beyond it are dropped for that client
  only, counted in :attr:`TcpClient.dropped`), a client that hangs up is forgotten.
  (pymavlink's own ``tcpin`` serves one client at a time: an idle one would lock the
  others out.)

MAVSDK's ``udpin://``, ``udpout://``, ``tcp://`` forms are accepted too, and its
``udp://:PORT`` (no host: listen on every interface) (:func:`vehicle_url`).

Framing (:class:`Framing`): a link speaks MAVLink 2 until its ground station shows it
reads only MAVLink 1, as PX4 (MAV_PROTO_VER 0) and ArduPilot negotiate it: a ground
station that can read MAVLink 2 switches to it on the first MAVLink 2 frame it hears
(QGroundControl, Mission Planner, pymavlink's ``mavutil``; MAVSDK always sends 2), so
one still writing MAVLink 1 :data:`MAVLINK1_AFTER_S` after it was first heard (and
greeted in MAVLink 2), and never MAVLink 2, gets MAVLink 1 frames from then on, until
it writes a MAVLink 2 frame. What the vehicle knows of a ground station's version is
the link's (:class:`Versions`): the same system and component ids on another link are
another ground station. On a MAVLink 1 link, messages with an id above 255 (MAVLink 2 only:
TUNNEL, PROTOCOL_VERSION...) are not sent, and extension fields are left out; a
PROTOCOL_VERSION asked for goes in MAVLink 2 framing all the same, as PX4 sends it.
"""

from __future__ import annotations

import contextlib
import itertools
import socket
from collections.abc import Iterator, Sequence
from typing import Any

from envs.vehicle.protocol import Peer
from planner.mavlink import mavutil

mavlink = mavutil.mavlink

TCP_BUFFER_BYTES = 1 << 20  # per TCP client: what it has not read yet, at most
TCP_SEND_BUFFER_BYTES = 1 << 16  # the kernel's send buffer per TCP client (SO_SNDBUF)
TCP_BACKLOG = 8
MAX_MESSAGES_PER_POLL = 1000  # per link and poll: a flood never starves the loop
MAVLINK1_AFTER_S = 2.0  # wall seconds a ground station has to switch to MAVLink 2
UDP_PEER_TIMEOUT_S = 60.0  # wall seconds of silence after which a udpin address is dropped
MAX_UDP_PEERS = 256  # addresses per udpin port; beyond, the one silent longest is dropped

_SCHEMES = {"udpin://": "udpin:", "udpout://": "udpout:", "udp://": "udpin:",
            "tcpin://": "tcpin:", "tcp://": "tcp:", "tcpout://": "tcp:"}
_PYMAVLINK = ("udpin:", "udpout:", "udp:", "udpbcast:", "tcpin:", "tcp:")


class ConnectionURLError(ValueError):
    """A connection URL the vehicle cannot open (one line)."""


def vehicle_url(url: str) -> str:
    """The pymavlink form of a vehicle-side URL (MAVSDK ``scheme://`` forms accepted)."""
    u = url.strip()
    for scheme, py in _SCHEMES.items():
        if u.startswith(scheme):
            u = py + u[len(scheme):]
            break
    if not u.startswith(_PYMAVLINK):
        raise ConnectionURLError(
            f"unsupported connection URL {url!r}: use udpin:HOST:PORT, udpout:HOST:PORT, "
            "tcpin:HOST:PORT or tcp:HOST:PORT")
    scheme, rest = u.split(":", 1)
    host, _, port = rest.rpartition(":")
    try:
        p = int(port)
    except ValueError:
        raise ConnectionURLError(f"bad connection URL {url!r}: port {port!r} "
                                 "is not a number") from None
    if not 0 < p < 65536:
        raise ConnectionURLError(f"bad connection URL {url!r}: port {p} is not in 1..65535")
    if not host and scheme in ("udpin", "udp", "tcpin"):
        return f"{scheme}:0.0.0.0:{p}"  # MAVSDK's "udp://:14540": every interface
    if not host:
        raise ConnectionURLError(f"bad connection URL {url!r}: expected HOST:PORT")
    return u


def is_mavlink1(msg: Any) -> bool:
    """Whether a received message came in MAVLink 1 framing."""
    buf = msg.get_msgbuf()
    return bool(buf) and buf[0] == mavlink.PROTOCOL_MARKER_V1


class Versions:
    """What the vehicle knows of each ground station's MAVLink on one link (by system and
    component id): when it was first heard and whether it ever sent MAVLink 2. Each link
    has its own (:class:`Framing`): two ground stations with the same ids on two links
    (a MAVLink 1 one and a MAVLink 2 one) are two ground stations."""

    MAX_SOURCES = 1024

    def __init__(self) -> None:
        self.first_heard: dict[tuple[int, int], float] = {}
        self.speaks_2: set[tuple[int, int]] = set()

    def reads_only_1(self, source: tuple[int, int], mavlink1: bool, now: float) -> bool:
        """Record a frame of ``source``; whether it is known to read MAVLink 1 only (it
        still writes MAVLink 1 :data:`MAVLINK1_AFTER_S` after it was first heard, and never
        wrote MAVLink 2)."""
        if len(self.first_heard) >= self.MAX_SOURCES:
            self.first_heard.clear()
            self.speaks_2.clear()
        first = self.first_heard.setdefault(source, now)
        if not mavlink1:
            self.speaks_2.add(source)
            return False
        return source not in self.speaks_2 and now - first >= MAVLINK1_AFTER_S


class Framing:
    """The MAVLink version a link's ground station reads (see the module docstring):
    ``heard(source, mavlink1, now)`` for every frame received on the link (``source``:
    system and component id); ``mavlink1`` says how to send. A ground station that ever
    sent a MAVLink 2 frame on the link reads MAVLink 2: when it starts again in MAVLink 1
    there (QGroundControl restarted, from the same address) it is sent MAVLink 2, so it
    switches back."""

    def __init__(self) -> None:
        self.mavlink1 = False
        self.versions = Versions()  # this link's ground stations

    def heard(self, source: tuple[int, int], mavlink1: bool, now: float) -> None:
        only_1 = self.versions.reads_only_1(source, mavlink1, now)
        if not mavlink1:
            self.mavlink1 = False
        elif only_1:
            self.mavlink1 = True

    def can_send(self, msg_id: int, mavlink2: bool = False) -> bool:
        """Whether message ``msg_id`` can go on this link (``mavlink2``: forced)."""
        return msg_id <= 255 or mavlink2 or not self.mavlink1


class MavPort:
    """One pymavlink connection (udpin, udpout, tcp): one link."""

    def __init__(self, url: str, sysid: int, compid: int) -> None:
        u = vehicle_url(url)
        scheme, rest = u.split(":", 1)
        if scheme in ("udpin", "udp"):
            # pymavlink binds with SO_REUSEADDR: two vehicles could share a port unnoticed
            host, _, port = rest.rpartition(":")
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
                try:
                    probe.bind((host, int(port)))
                except OSError as exc:
                    raise ConnectionURLError(f"cannot listen on {url}: "
                                             f"{exc.strerror or exc}") from None
        try:
            self.conn = mavutil.mavlink_connection(u, source_system=sysid,
                                                   source_component=compid,
                                                   autoreconnect=False, retries=0,
                                                   reconnect_delay=0.1)
        except (OSError, ValueError) as exc:
            raise ConnectionURLError(
                f"cannot open {url}: {getattr(exc, 'strerror', None) or exc}") from None
        self.url = url
        self.mav = self.conn.mav
        self.closed = False
        self.framing = Framing()

    def fileno(self) -> int | None:
        return self.conn.fd

    def receive(self) -> Iterator[Any]:
        for _ in range(MAX_MESSAGES_PER_POLL):
            try:
                msg = self.conn.recv_msg()
            except (OSError, ValueError):
                return
            if msg is None:
                return
            yield msg

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.conn.close()


class UdpListener:
    """A ``udpin:HOST:PORT`` port: a bound socket; each address that writes is a
    :class:`UdpPeer` (see the module docstring)."""

    def __init__(self, url: str, sysid: int, compid: int) -> None:
        host, _, port = vehicle_url(url).split(":", 1)[1].rpartition(":")
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((host, int(port)))  # no SO_REUSEADDR: a port in use is an error
            sock.setblocking(False)
        except OSError as exc:
            sock.close()
            raise ConnectionURLError(f"cannot listen on {url}: {exc.strerror or exc}") from None
        self.url = url
        self.sock = sock
        self.sysid, self.compid = sysid, compid
        self.peers: dict[tuple, UdpPeer] = {}
        self.latest: tuple | None = None  # the address that wrote last

    def fileno(self) -> int | None:
        return self.sock.fileno()

    def read(self) -> list[tuple[tuple, bytes]]:
        """(address, datagram) for what is waiting (at most MAX_MESSAGES_PER_POLL)."""
        out = []
        for _ in range(MAX_MESSAGES_PER_POLL):
            try:
                data, addr = self.sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. an ICMP error of an earlier send: not ours to end
                continue
            out.append((addr, data))
            self.latest = addr
        return out

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()


class UdpPeer:
    """One address writing to a ``udpin`` port: a link with its own parser, encoder and
    framing; what it sent waits in :attr:`pending` until :meth:`receive`."""

    def __init__(self, listener: UdpListener, address: tuple, now: float | None) -> None:
        self.listener = listener
        self.address = address
        self.url = f"udp peer {address[0]}:{address[1]}"
        self.pending: list[bytes] = []
        self.last_rx = now
        self.closed = False
        self.mav = mavlink.MAVLink(self, srcSystem=listener.sysid, srcComponent=listener.compid)
        self.mav.robust_parsing = True
        self.framing = Framing()

    def fileno(self) -> int | None:
        return None if self.closed else self.listener.fileno()

    def write(self, buf: bytes) -> None:
        if not self.closed:
            with contextlib.suppress(OSError):
                self.listener.sock.sendto(buf, self.address)

    def receive(self) -> Iterator[Any]:
        pending, self.pending = self.pending, []
        for data in pending:
            yield from self.mav.parse_buffer(data) or ()

    def close(self) -> None:
        self.closed = True
        if self.listener.peers.get(self.address) is self:
            del self.listener.peers[self.address]


class TcpClient:
    """One ground station connected to a ``tcpin`` port (non-blocking; see the module
    docstring). ``mav`` encodes into its buffer (``write``) and parses what it sends."""

    def __init__(self, sock: socket.socket, address: tuple, sysid: int, compid: int) -> None:
        sock.setblocking(False)
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, TCP_SEND_BUFFER_BYTES)
        self.sock = sock
        self.address = address
        self.url = f"tcp client {address[0]}:{address[1]}"
        self.out = bytearray()
        self.dropped = 0  # messages not queued: the client did not read
        self.closed = False
        self.mav = mavlink.MAVLink(self, srcSystem=sysid, srcComponent=compid)
        self.mav.robust_parsing = True
        self.framing = Framing()

    def fileno(self) -> int | None:
        return None if self.closed else self.sock.fileno()

    def write(self, buf: bytes) -> None:
        """Queue one encoded message (whole, or not at all) and send what the socket
        takes now."""
        if self.closed:
            return
        if len(self.out) + len(buf) > TCP_BUFFER_BYTES:
            self.dropped += 1
            return
        self.out += buf
        self.flush()

    def flush(self) -> None:
        if self.closed or not self.out:
            return
        try:
            n = self.sock.send(self.out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self.close()
            return
        del self.out[:n]

    def receive(self) -> Iterator[Any]:
        if self.closed:
            return
        self.flush()
        for _ in range(64):  # at most 4 MB per poll
            try:
                data = self.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.close()
                return
            if not data:
                self.close()
                return
            yield from self.mav.parse_buffer(data) or ()

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            with contextlib.suppress(OSError):
                self.sock.close()


class TcpListener:
    """A ``tcpin:HOST:PORT`` port: accepts any number of ground stations."""

    def __init__(self, url: str, sysid: int, compid: int) -> None:
        host, _, port = vehicle_url(url).split(":", 1)[1].rpartition(":")
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((host, int(port)))
            sock.listen(TCP_BACKLOG)
            sock.setblocking(False)
        except OSError as exc:
            sock.close()
            raise ConnectionURLError(f"cannot listen on {url}: {exc.strerror or exc}") from None
        self.url = url
        self.sock = sock
        self.sysid, self.compid = sysid, compid

    def fileno(self) -> int | None:
        return self.sock.fileno()

    def accept(self) -> list[TcpClient]:
        out = []
        for _ in range(TCP_BACKLOG):
            try:
                conn, addr = self.sock.accept()
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break
            out.append(TcpClient(conn, addr, self.sysid, self.compid))
        return out

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()


Link = MavPort | TcpClient | UdpPeer


class Links:
    """Every port of the vehicle and the links on them (see the module docstring)."""

    def __init__(self, urls: Sequence[str], sysid: int, compid: int) -> None:
        self.links: dict[int, Link] = {}
        self.listeners: list[TcpListener | UdpListener] = []
        self._ids = itertools.count()
        self.sent = 0
        self.gone: list[int] = []  # ids of links closed since the last take_gone()
        try:
            for url in urls:
                scheme = vehicle_url(url).split(":", 1)[0]
                if scheme == "tcpin":
                    self.listeners.append(TcpListener(url, sysid, compid))
                elif scheme in ("udpin", "udp"):
                    self.listeners.append(UdpListener(url, sysid, compid))
                else:
                    self.links[next(self._ids)] = MavPort(url, sysid, compid)
        except BaseException:
            self.close()
            raise

    def poll(self, now: float | None = None) -> Iterator[tuple[int, Any]]:
        """(link id, message) for everything received; new TCP clients are accepted;
        each link's framing follows what it hears (``now``: wall seconds)."""
        for lst in self.listeners:
            if isinstance(lst, TcpListener):
                for client in lst.accept():
                    self.links[next(self._ids)] = client
                continue
            for addr, data in lst.read():
                peer = lst.peers.get(addr)
                if peer is None:
                    if len(lst.peers) >= MAX_UDP_PEERS:  # a flood of addresses: bounded
                        min(lst.peers.values(), key=lambda q: q.last_rx or 0.0).close()
                    peer = lst.peers[addr] = UdpPeer(lst, addr, now)
                    self.links[next(self._ids)] = peer
                peer.pending.append(data)
                peer.last_rx = now
            if now is not None:  # forget the silent ones (never the last that wrote)
                for addr, peer in list(lst.peers.items()):
                    if addr != lst.latest and peer.last_rx is not None \
                            and now - peer.last_rx > UDP_PEER_TIMEOUT_S:
                        peer.close()
        for k, link in list(self.links.items()):
            for msg in link.receive():
                if now is not None and msg.get_type() != "BAD_DATA":
                    link.framing.heard((msg.get_srcSystem(), msg.get_srcComponent()),
                                       is_mavlink1(msg), now)
                yield k, msg
            if link.closed:
                del self.links[k]
                self.gone.append(k)

    def take_gone(self) -> list[int]:
        """The ids of the links closed since the last call."""
        gone, self.gone = self.gone, []
        return gone

    def fds(self) -> list[int] | None:
        """The file descriptors to wait on (None: a link has none, sleep instead)."""
        fds = [lst.fileno() for lst in self.listeners] + \
            [link.fileno() for link in self.links.values() if not link.closed]
        if any(fd is None for fd in fds):
            return None
        return [fd for fd in fds if fd is not None]

    @staticmethod
    def _send(link: Link, msg: Any, mavlink2: bool = False) -> int:
        """Send ``msg`` on ``link`` in its framing; 1 if sent."""
        if not link.framing.can_send(msg.id, mavlink2):
            return 0
        with contextlib.suppress(OSError):
            link.mav.send(msg, force_mavlink1=link.framing.mavlink1 and not mavlink2)
            return 1
        return 0

    def broadcast(self, msg: Any) -> None:
        """``msg`` on every link."""
        if msg is None:
            return
        for link in list(self.links.values()):
            self.sent += self._send(link, msg)

    def ids(self) -> list[int]:
        """The ids of the links open now."""
        return list(self.links)

    def send_on(self, link_id: int, msg: Any, *, mavlink2: bool = False) -> None:
        """``msg`` on link ``link_id`` (gone: nothing); ``mavlink2``: in MAVLink 2
        framing whatever the link's."""
        link = self.links.get(link_id)
        if msg is None or link is None:
            return
        self.sent += self._send(link, msg, mavlink2)

    def send(self, peer: Peer, msg: Any, *, mavlink2: bool = False) -> None:
        """``msg`` on the link of ``peer`` (:meth:`send_on`)."""
        self.send_on(peer[0], msg, mavlink2=mavlink2)

    def send_args(self, peer: Peer, name: str, args: tuple) -> None:
        """``<name>_send(target system, target component, *args)`` to ``peer``."""
        link = self.links.get(peer[0])
        if link is None or not link.framing.can_send(
                getattr(mavlink, f"MAVLink_{name}_message").id):
            return
        with contextlib.suppress(OSError):
            getattr(link.mav, f"{name}_send")(peer[1], peer[2], *args,
                                              force_mavlink1=link.framing.mavlink1)
            self.sent += 1

    def close(self) -> None:
        for link in self.links.values():
            link.close()
        for lst in self.listeners:
            lst.close()
