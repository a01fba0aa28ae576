"""A VRPN tracker server, the live humanoid as `vrpn_Tracker` reports to any VRPN client, written from VRPN's
protocol description and sources (Format_Of_Protocol.txt, vrpn_Connection.C, vrpn_Tracker.C): TCP and UDP on
one port, non-blocking sockets on the caller's selector (docs/streams.md#vrpn-the-live-humanoid-as-a-vrpn-tracker).
"""

from __future__ import annotations

import errno
import logging
import selectors
import socket
import struct
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from flockcal.clock import Clock

log = logging.getLogger(__name__)

DEFAULT_PORT = 3883  # vrpn_DEFAULT_LISTEN_PORT_NO
MAGIC = b"vrpn: ver. 07.38"  # vrpn_MAGIC: a client accepts any 07.xx (the major version up to the last '.')
ALIGN = 8  # vrpn_ALIGN: header and payload each padded to a multiple of 8 bytes
HEADER = 24  # length, seconds, microseconds, sender, type and the (sniffers') sequence number: 5 + 1 words
COOKIE_SIZE = 24  # the magic, two spaces, the remote log mode ('0'..'3'), NUL padding
UDP_MAX = 1472  # vrpn_CONNECTION_UDP_BUFLEN: a client reads at most this much of a datagram

# System message types (negative) and their meaning, vrpn_Connection.h.
SENDER_DESCRIPTION, TYPE_DESCRIPTION, UDP_DESCRIPTION, LOG_DESCRIPTION = -1, -2, -3, -4

# What the server says (its own type numbers, which each client maps through the descriptions sent when it
# connects) and the client messages it answers.
POS_QUAT = "vrpn_Tracker Pos_Quat"
TO_ROOM = "vrpn_Tracker To_Room"
UNIT_TO_SENSOR = "vrpn_Tracker Unit_To_Sensor"
PONG = "vrpn_Base pong_message"
TYPES = (POS_QUAT, TO_ROOM, UNIT_TO_SENSOR, PONG)
PING = "vrpn_Base ping_message"
REQUEST_TO_ROOM = "vrpn_Tracker Request_Tracker_To_Room"
REQUEST_UNIT_TO_SENSOR = "vrpn_Tracker Request_Unit_To_Sensor"

COOKIE_TIMEOUT_S = 10.0  # a client that has not sent its cookie by then is dropped
MAX_MESSAGE = 64000  # vrpn_CONNECTION_TCP_BUFLEN: a longer message is no VRPN client's
SEND_BUFFER = 64 * 1024  # kernel send buffer of a client's TCP socket (Linux doubles it)
BACKLOG = 64 * 1024  # reports waiting for a TCP client beyond that: it has stopped reading (~1 s at 144 Hz)

# One Pos_Quat message as it travels: the header, then vrpn_Tracker::encode_to's payload (the sensor, the
# sensor again to align the doubles, position x y z in metres, quaternion x y z w), all big-endian.
REPORT = np.dtype([("length", ">u4"), ("sec", ">u4"), ("usec", ">u4"), ("sender", ">i4"), ("type", ">i4"),
                   ("seq", ">u4"), ("sensor", ">i4"), ("sensor_pad", ">i4"), ("pos", ">f8", 3), ("quat", ">f8", 4)])


def cookie(log_mode: int = 0) -> bytes:
    """The connection's first 24 bytes from either side (write_vrpn_cookie)."""
    return (MAGIC + b"  " + str(log_mode).encode()).ljust(COOKIE_SIZE, b"\0")


def cookie_ok(data: bytes) -> bool:
    """Whether a peer's cookie is VRPN's of this major version (check_vrpn_cookie: through the last '.')."""
    head = MAGIC[: MAGIC.rindex(b".") + 1]
    return data[: len(head)] == head and data[len(MAGIC) + 2: len(MAGIC) + 3] in b"0123"


def padded(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


def message(type_id: int, sender_id: int, payload: bytes, when: float, seq: int = 0) -> bytes:
    """One message (vrpn_Endpoint::marshall_message), sent at `when` (unix s): the header's length counts the
    header and the payload but not the payload's padding, which the reader infers."""
    sec = int(when)
    head = struct.pack(">IIIiiI", HEADER + len(payload), sec & 0xFFFFFFFF, int((when - sec) * 1e6), sender_id,
                       type_id, seq & 0xFFFFFFFF)
    return head + payload.ljust(padded(len(payload)), b"\0")


def description(kind: int, number: int, name: str, when: float) -> bytes:
    """A sender or type description: the name's length with its NUL, then the name and the NUL."""
    raw = name.encode() + b"\0"
    return message(kind, number, len(raw).to_bytes(4, "big") + raw, when)


class ReportPacker:
    """Pos_Quat messages of a fixed set of sensors, one frame's at a time into a buffer kept between calls
    (the header's constant fields written once): `frames` returns each frame's messages as one bytes."""

    def __init__(self, sensors, sender: int = 0, type_id: int = 0, frames: int = 64):
        self.sensors = np.asarray(sensors)
        self._buf = np.zeros((frames, len(self.sensors)), dtype=REPORT)
        self._buf["length"] = HEADER + 64
        self._buf["sender"], self._buf["type"] = sender, type_id
        self._buf["sensor"] = self._buf["sensor_pad"] = self.sensors
        # The fields' views made once: the streams pack 2-3 frames ~70 times a second, where making a
        # field's view costs about as much as filling it.
        self._fields = tuple(self._buf[k] for k in ("sec", "usec", "pos", "quat"))
        self._row = self._buf.itemsize * len(self.sensors)

    def frames(self, wall_times, positions: np.ndarray, quats: np.ndarray, finite: bool = False) -> list[bytes]:
        """`positions` (n, K, 3) metres, `quats` (n, K, 4) x y z w, `wall_times` (n,) unix seconds (a sequence
        of floats): per frame the messages of its sensors with a position (a sensor with NaN, no pose yet, is
        left out; `finite`: the caller knows there is none)."""
        out = []
        sec_f, usec_f, pos_f, quat_f = self._fields
        for at in range(0, len(wall_times), len(self._buf)):
            n = min(len(self._buf), len(wall_times) - at)
            # Frame by frame in Python: the streams pack two or three at a time, where each array call costs
            # more than these few numbers' arithmetic.
            for i, when in enumerate(wall_times[at:at + n]):
                sec = int(when)  # the floor: wall times are positive
                sec_f[i], usec_f[i] = sec, int((when - sec) * 1e6)  # truncated, as a cast to an integer is
            pos = positions[at:at + n]
            pos_f[:n], quat_f[:n] = pos, quats[at:at + n]
            # A sensor with no pose has NaN in its position (its rotation too makes the position NaN); a sum
            # is finite only when every term is.
            if finite or np.isfinite(np.add.reduce(pos, axis=None)):
                raw = self._buf[:n].tobytes()
                out += [raw[i:i + self._row] for i in range(0, len(raw), self._row)]
            else:
                ok = np.isfinite(pos).all(axis=2)
                out += [row[keep].tobytes() for row, keep in zip(self._buf[:n], ok) if keep.any()]
        return out


def to_room_payload() -> bytes:
    """encode_tracker2room_to: the tracker-to-room transform, none (reports are already in the room's frame)."""
    return np.array([0, 0, 0, 0, 0, 0, 1], dtype=">f8").tobytes()


def unit_to_sensor_payload(sensor: int) -> bytes:
    """encode_unit2sensor_to: no unit offset on any sensor (each report is its segment's own pose)."""
    return np.array([sensor, 0], dtype=">i4").tobytes() + np.array([0, 0, 0, 0, 0, 0, 1], dtype=">f8").tobytes()


class Drop(StrEnum):
    """Why a client was let go (counted in `VrpnServer.status()`'s `dropped`)."""

    SLOW = "slow"  # its TCP backlog passed the bound: it stopped reading
    CLOSED = "closed"  # it hung up, or its socket failed
    PROTOCOL = "protocol"  # not a VRPN 07 client, or a message no client sends
    COOKIE_TIMEOUT = "cookie_timeout"  # it never finished connecting
    REFUSED = "refused"  # max_clients were already connected


@dataclass
class Client:
    """One VRPN connection: its TCP socket, what it described of itself, what waits to be sent to it."""

    sock: socket.socket
    address: tuple  # the peer's TCP address
    tcp_only: bool  # it connected to the TCP port itself (no UDP channel will come)
    since: float  # when it came (unix s, shown in /api/status)
    started: float  # ... on the monotonic clock (the cookie's deadline)
    state: str = "cookie"  # connecting (the server calls back) | cookie (waiting for the peer's) | connected
    inbox: bytearray = field(default_factory=bytearray)
    outbox: bytearray = field(default_factory=bytearray)
    udp: tuple | None = None  # where its reports go once it described its UDP port
    udp_sock: socket.socket | None = None  # ... connected there (no address to read and route to look up per datagram)
    types: dict = field(default_factory=dict)  # the client's type numbers → names
    senders: dict = field(default_factory=dict)  # the client's sender numbers → names

    @property
    def label(self) -> str:
        return f"{self.address[0]}:{self.address[1]}"


class VrpnServer:
    """The tracker `device` (VRPN's sender name) on `port` of `host`, TCP and UDP, driven by the caller's
    selector (`register`); `send_reports` hands out one datagram (or TCP write) per frame to every client.

    A client whose TCP backlog (what its socket would not take) passes `backlog_bytes` has stopped reading
    and is dropped, as the websocket's slow clients are; UDP reports are fire-and-forget, from a socket
    connected to each client. The caller makes the calls one at a time (server/outputs.py's lock):
    `send_reports` may come from another thread than the one that waits in the selector."""

    def __init__(self, host: str, port: int, clock: Clock, device: str = "flockcal", sensors: int = 16,
                 max_clients: int = 32, backlog_bytes: int = BACKLOG):
        self.clock = clock
        self.device = device
        self.sensors = sensors
        self.max_clients = max_clients
        self.backlog_bytes = backlog_bytes
        self.clients: list[Client] = []
        self.dropped: dict[Drop, int] = dict.fromkeys(Drop, 0)
        self.reports = 0
        self.seq = 0
        self.streaming = False  # whether a client is connected (the streams ask before each frame's work)
        self._sel: selectors.BaseSelector | None = None
        self.tcp, self.udp_in, self.port = _bind(host, port)

    # -- sockets ------------------------------------------------------------------------------------------
    def register(self, sel: selectors.BaseSelector) -> None:
        self._sel = sel
        sel.register(self.tcp, selectors.EVENT_READ, self._accept)
        sel.register(self.udp_in, selectors.EVENT_READ, self._lobbed)

    def close(self) -> None:
        for c in list(self.clients):
            self._drop(c, None)
        for s in (self.tcp, self.udp_in):
            if self._sel is not None:
                try:
                    self._sel.unregister(s)
                except (KeyError, ValueError):
                    pass
            s.close()

    def _accept(self, _mask) -> None:
        for _ in range(16):
            try:
                sock, addr = self.tcp.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # out of descriptors: the next wake-up tries again
                log.warning("VRPN: cannot accept a client: %s", exc.strerror or exc)
                return
            if len(self.clients) >= self.max_clients:
                self.dropped[Drop.REFUSED] += 1
                sock.close()
                continue
            self._add(Client(sock, addr, True, self.clock.wall(), self.clock.monotonic()))

    def _lobbed(self, _mask) -> None:
        """Connection requests (vrpn_udp_request_lob_packet): "HOST PORT" asks to be called back on TCP PORT.
        The call goes to the address the request came from, not the one it names, so a forged request cannot
        turn the server on another machine; a client repeats its request every 2 s until called."""
        for _ in range(16):
            try:
                data, (ip, *_rest) = self.udp_in.recvfrom(256)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            try:
                _host, port_text = data.split(b"\0", 1)[0].decode("ascii").split()
                port = int(port_text)
            except (UnicodeDecodeError, ValueError):
                continue  # not a VRPN request (VRPN ignores those too)
            if not 1024 <= port <= 65535:
                continue
            if any(c.address[:2] == (ip, port) for c in self.clients):
                continue  # a repeat of a request already being served
            if len(self.clients) >= self.max_clients:
                self.dropped[Drop.REFUSED] += 1
                continue
            sock = socket.socket(self.tcp.family, socket.SOCK_STREAM)
            sock.setblocking(False)
            err = sock.connect_ex((ip, port))
            if err not in (0, errno.EINPROGRESS):
                sock.close()
                continue
            self._add(Client(sock, (ip, port), False, self.clock.wall(), self.clock.monotonic(), state="connecting"))

    def _add(self, c: Client) -> None:
        c.sock.setblocking(False)
        c.sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        c.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        # A fixed kernel buffer (no autotuning up to megabytes): a client that stops reading shows within
        # about a second of reports, not a minute.
        c.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        self.clients.append(c)
        if c.state == "connecting":
            self._sel.register(c.sock, selectors.EVENT_WRITE, lambda mask, c=c: self._ready(c, mask))
        else:
            self._sel.register(c.sock, selectors.EVENT_READ, lambda mask, c=c: self._ready(c, mask))
            self._send(c, cookie())
        log.info("VRPN: client %s connecting (%s)", c.label, "TCP only" if c.tcp_only else "called back")

    def _ready(self, c: Client, mask: int) -> None:
        if c.state == "connecting":
            err = c.sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
            if err:
                self._drop(c, Drop.CLOSED)
                return
            c.state = "cookie"
            self._send(c, cookie())
        if mask & selectors.EVENT_WRITE and c.outbox:
            self._flush(c)
        if mask & selectors.EVENT_READ and c in self.clients:
            self._read(c)
        if c in self.clients:
            want = selectors.EVENT_READ | (selectors.EVENT_WRITE if c.outbox else 0)
            self._sel.modify(c.sock, want, lambda mask, c=c: self._ready(c, mask))

    # -- what clients say ---------------------------------------------------------------------------------
    def _read(self, c: Client) -> None:
        try:
            data = c.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._drop(c, Drop.CLOSED)
            return
        if not data:
            self._drop(c, Drop.CLOSED)
            return
        c.inbox += data
        if c.state == "cookie":
            if len(c.inbox) < COOKIE_SIZE:
                return
            if not cookie_ok(bytes(c.inbox[:COOKIE_SIZE])):
                log.warning("VRPN: client %s is no VRPN 07 client (cookie %r); dropped", c.label,
                            bytes(c.inbox[:len(MAGIC)]))
                self._drop(c, Drop.PROTOCOL)
                return
            del c.inbox[:COOKIE_SIZE]
            c.state = "connected"
            self.streaming = True
            now = self.clock.wall()
            self._send(c, description(SENDER_DESCRIPTION, 0, self.device, now)
                       + b"".join(description(TYPE_DESCRIPTION, k, name, now) for k, name in enumerate(TYPES)))
            log.info("VRPN: client %s connected", c.label)
        while len(c.inbox) >= HEADER:
            length, _sec, _usec, sender, kind = struct.unpack_from(">iIIii", c.inbox)
            size = length - HEADER
            if size < 0 or size > MAX_MESSAGE:
                self._drop(c, Drop.PROTOCOL)
                return
            if len(c.inbox) < HEADER + padded(size):
                return
            payload = bytes(c.inbox[HEADER: HEADER + size])
            del c.inbox[:HEADER + padded(size)]
            self._handle(c, kind, sender, payload)
            if c not in self.clients:
                return

    def _handle(self, c: Client, kind: int, sender: int, payload: bytes) -> None:
        if kind in (SENDER_DESCRIPTION, TYPE_DESCRIPTION):
            n = int.from_bytes(payload[:4], "big")
            name = payload[4: 4 + n].split(b"\0", 1)[0].decode("latin-1")
            (c.senders if kind == SENDER_DESCRIPTION else c.types)[sender] = name
        elif kind == UDP_DESCRIPTION and not c.tcp_only:
            # The sender field holds the port; reports go to the TCP peer's address (see `_lobbed`).
            if 0 < sender < 65536:
                udp = socket.socket(self.tcp.family, socket.SOCK_DGRAM)
                udp.setblocking(False)
                try:
                    udp.connect((c.address[0], sender))
                except OSError as exc:  # no route to it: its reports go over TCP
                    udp.close()
                    log.warning("VRPN: client %s: cannot send to its UDP port %d: %s", c.label, sender,
                                exc.strerror or exc)
                    return
                if c.udp_sock is not None:
                    c.udp_sock.close()
                c.udp, c.udp_sock = (c.address[0], sender), udp
        elif kind >= 0 and c.senders.get(sender) == self.device:
            what, now = c.types.get(kind), self.clock.wall()
            if what == PING:
                self._send(c, message(TYPES.index(PONG), 0, b"", now))
            elif what == REQUEST_TO_ROOM:
                self._send(c, message(TYPES.index(TO_ROOM), 0, to_room_payload(), now))
            elif what == REQUEST_UNIT_TO_SENSOR:
                self._send(c, b"".join(message(TYPES.index(UNIT_TO_SENSOR), 0, unit_to_sensor_payload(k), now)
                                       for k in range(self.sensors)))

    # -- what the server says -----------------------------------------------------------------------------
    def _send(self, c: Client, data: bytes) -> None:
        """Write to the client's TCP socket without waiting: what it does not take waits in its outbox."""
        if c.outbox:
            c.outbox += data
        else:
            try:
                sent = c.sock.send(data)
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError:
                self._drop(c, Drop.CLOSED)
                return
            if sent < len(data):
                c.outbox += data[sent:]
                if c.state != "connecting" and self._sel is not None:
                    self._sel.modify(c.sock, selectors.EVENT_READ | selectors.EVENT_WRITE,
                                     lambda mask, c=c: self._ready(c, mask))
        if len(c.outbox) > self.backlog_bytes:
            log.warning("VRPN: client %s stopped reading (%d KB waiting); dropped", c.label, len(c.outbox) // 1024)
            self._drop(c, Drop.SLOW)

    def _flush(self, c: Client) -> None:
        try:
            sent = c.sock.send(c.outbox)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._drop(c, Drop.CLOSED)
            return
        del c.outbox[:sent]

    def send_reports(self, frames: list[bytes]) -> None:
        """One frame's Pos_Quat messages per item (`ReportPacker.frames`, at most UDP_MAX bytes),
        to every connected client: a datagram each over UDP, else on its TCP stream."""
        for c in list(self.clients):
            if c.state != "connected":
                continue
            if c.udp_sock is not None:
                send = c.udp_sock.send
                for data in frames:
                    try:
                        send(data)
                    except (BlockingIOError, InterruptedError):
                        pass  # the socket's buffer is full: this report is lost, as UDP's may be
                    except OSError:
                        pass  # an unreachable client: its TCP side tells when it is gone
            else:
                self._send(c, b"".join(frames))
        self.reports += len(frames)

    def tick(self, now: float) -> None:
        """Drop clients that never finished connecting."""
        for c in list(self.clients):
            if c.state != "connected" and now - c.started > COOKIE_TIMEOUT_S:
                self._drop(c, Drop.COOKIE_TIMEOUT)

    def _drop(self, c: Client, why: Drop | None) -> None:
        if c not in self.clients:
            return
        self.clients.remove(c)
        self.streaming = any(other.state == "connected" for other in self.clients)
        if c.udp_sock is not None:
            c.udp_sock.close()
        if why is not None:
            self.dropped[why] += 1
            log.info("VRPN: client %s gone (%s)", c.label, why)
        if self._sel is not None:
            try:
                self._sel.unregister(c.sock)
            except (KeyError, ValueError):
                pass
        c.sock.close()

    def status(self) -> dict:
        return {"port": self.port, "device": self.device,
                "clients": [{"address": c.label, "state": c.state,
                             "channel": "udp" if c.udp is not None else "tcp", "since": round(c.since, 3)}
                            for c in self.clients],
                "reports": self.reports, "dropped": {why.value: n for why, n in self.dropped.items()}}


def _bind(host: str, port: int) -> tuple[socket.socket, socket.socket, int]:
    """The TCP listener and the UDP request socket on one port number (0: one the system picks for both).
    Raises OSError (EADDRINUSE: another server has the port)."""
    family = socket.getaddrinfo(host, port or None, type=socket.SOCK_STREAM)[0][0]
    for _attempt in range(20 if port == 0 else 1):
        tcp = socket.socket(family, socket.SOCK_STREAM)
        udp = socket.socket(family, socket.SOCK_DGRAM)
        try:
            tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            tcp.bind((host, port))
            chosen = tcp.getsockname()[1]
            udp.bind((host, chosen))
            tcp.listen(16)
            tcp.setblocking(False)
            udp.setblocking(False)
            return tcp, udp, chosen
        except OSError as exc:
            tcp.close()
            udp.close()
            if port != 0 or exc.errno != errno.EADDRINUSE:
                raise
    raise OSError(errno.EADDRINUSE, "no port free for both TCP and UDP")
