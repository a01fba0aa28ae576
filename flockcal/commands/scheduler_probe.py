"""Whether `flockcal batch --scheduler ADDRESS` leads to a Dask scheduler, found out on a plain socket first.

A Dask scheduler greets every connection at once with a length-prefixed message; anything else at that
address (the dashboard's HTTP server on 8787, a silent listener, an SSH daemon) would leave Dask's own
client hanging past its timeout, or reading "HTTP/1.1" as a frame length. The probe needs no Dask import.
"""

from __future__ import annotations

import socket
import struct
import time

from flockcal.errors import UserError

# A Dask handshake is a few hundred bytes; a first word above this is not a message length.
MAX_GREETING = 64 * 2**20
# After this much silence (a Dask scheduler greets within milliseconds), nudge the peer with bytes that make
# an HTTP server answer (400) and that a Dask scheduler that is merely slow reads as an empty message.
NUDGE_AFTER_S = 1.0
NUDGE = b"\0" * 8 + b" / HTTP/1.0\r\n\r\n"
HINT = "start one with `dask scheduler` and give its tcp://host:port (the scheduler's port, 8786 by default)"


def host_port(address: str) -> tuple[str, int] | None:
    """(host, port) of a tcp:// (or scheme-less host:port) address; None for schemes the probe cannot speak
    (tls://, ucx://, inproc://: Dask's own client checks those)."""
    scheme, sep, rest = address.partition("://")
    if not sep:
        scheme, rest = "tcp", address
    if scheme.lower() != "tcp":
        return None
    rest = rest.rstrip("/")
    if rest.startswith("["):  # [IPv6]:port
        host, _, port = rest[1:].partition("]")
        port = port.removeprefix(":")
    else:
        host, _, port = rest.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise UserError(f"--scheduler {address}: give the scheduler as tcp://HOST:PORT (e.g. tcp://10.0.0.5:8786)")
    return host, int(port)


def check_scheduler(address: str, timeout: float) -> None:
    """Return when `address` greets like a Dask scheduler within `timeout` seconds; otherwise a UserError
    naming the address and what was found there (refused, silent, an HTTP server, other bytes)."""
    hp = host_port(address)
    if hp is None:
        return
    deadline = time.monotonic() + timeout
    try:
        sock = socket.create_connection(hp, timeout=timeout)
    except socket.gaierror as exc:
        raise UserError(f"cannot reach the Dask scheduler at {address}: the host name {hp[0]!r} does not resolve "
                        f"({exc.strerror}); {HINT}") from None
    except TimeoutError:
        raise UserError(f"cannot reach the Dask scheduler at {address}: no answer to the connection within "
                        f"{timeout:g} s (the host is down, or a firewall drops the packets); {HINT}") from None
    except OSError as exc:
        raise UserError(f"cannot reach the Dask scheduler at {address}: {_reason(exc)}; {HINT}") from None
    with sock:
        first, closed = _first_bytes(sock, deadline)
    if first.startswith(b"HTTP/") or b"<html" in first.lower():
        line = first.split(b"\r\n", 1)[0].decode("latin-1").split(" (", 1)[0]
        status = line[:40] if first.startswith(b"HTTP/") else "a web page"
        raise UserError(f"{address} is not a Dask scheduler: an HTTP server answered ({status!r}; the Dask "
                        f"dashboard listens on 8787); {HINT}")
    if len(first) >= 8 and 0 < struct.unpack_from("<Q", first)[0] <= MAX_GREETING:
        return  # a length-prefixed message: Dask's greeting
    if first:
        raise UserError(f"{address} is not a Dask scheduler: it answered {_shown(first)}; {HINT}")
    if closed:
        raise UserError(f"{address} is not a Dask scheduler: it closed the connection without a greeting; {HINT}")
    raise UserError(f"{address} is not a Dask scheduler: it accepted the connection but sent nothing in "
                    f"{timeout:g} s (a scheduler greets at once); {HINT}")


def _first_bytes(sock: socket.socket, deadline: float) -> tuple[bytes, bool]:
    """What the peer sends first (up to 64 bytes, or a line), and whether it closed the connection; b"" and
    False when it stayed silent until `deadline`, even after the nudge."""
    got = bytearray()
    start = time.monotonic()
    nudge_at = start + min(NUDGE_AFTER_S, (deadline - start) / 2)
    nudged = False
    while len(got) < 64:
        now = time.monotonic()
        if now >= deadline:
            break
        if not nudged and not got and now >= nudge_at:
            try:
                sock.sendall(NUDGE)
            except OSError:
                return bytes(got), True
            nudged = True
        until = deadline if nudged or got else nudge_at
        sock.settimeout(max(0.01, until - now))
        try:
            data = sock.recv(64 - len(got))
        except TimeoutError:
            continue
        except OSError:
            return bytes(got), True
        if not data:
            return bytes(got), True
        got += data
        if (len(got) >= 8 and not got.startswith(b"HTTP/")) or b"\r\n" in got:
            break  # enough to tell a length prefix from a line of text
    return bytes(got), False


def _reason(exc: OSError) -> str:
    if isinstance(exc, ConnectionRefusedError):
        return "nothing listens there (connection refused)"
    return exc.strerror or str(exc)


def _shown(data: bytes) -> str:
    text = data[:40]
    if all(32 <= b < 127 or b in (9, 10, 13) for b in text):
        return repr(text.decode("ascii").strip())
    return "bytes " + text[:16].hex(" ")
