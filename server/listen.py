"""The listening socket of the service, with a bounded send buffer per client connection.

Accepted sockets inherit SO_SNDBUF from the listener; fixing it (instead of Linux's autotuning up to
megabytes) caps how much a stalled websocket client can have queued before its sends block and the
service drops it.
"""

from __future__ import annotations

import socket


def listen_socket(host: str, port: int, send_buffer: int | None) -> socket.socket:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    if send_buffer:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, int(send_buffer))
    sock.bind((host, port))
    sock.listen(128)
    sock.set_inheritable(True)
    return sock
