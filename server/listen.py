"""The listening socket of the service: a bounded send buffer and no Nagle delay per client connection.

Accepted sockets inherit SO_SNDBUF and TCP_NODELAY from the listener. Fixing the buffer (instead of
Linux's autotuning up to megabytes) caps how much a stalled websocket client can have queued before its
sends block and the service drops it; TCP_NODELAY sends each small websocket message at once.
"""

from __future__ import annotations

import socket


def listen_socket(host: str, port: int, send_buffer: int | None) -> socket.socket:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    # Named IPPROTO_TCP (not 0) so asyncio recognises accepted sockets as TCP; with proto 0 it leaves
    # Nagle on, and a pose message then waits for the client's delayed ACK: 20-40 ms stalls, p99 +25 ms.
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    if send_buffer:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, int(send_buffer))
    sock.bind((host, port))
    sock.listen(128)
    sock.set_inheritable(True)
    return sock
