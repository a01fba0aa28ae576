"""The service's listening socket: what each accepted client connection inherits (real loopback sockets)."""

from __future__ import annotations

import asyncio
import socket

from flockcal.server.listen import listen_socket


def test_accepted_connections_send_at_once_and_have_a_bounded_buffer():
    """An asyncio server on the listener (as uvicorn runs it) gets connections with Nagle off and the
    fixed send buffer. With Nagle on, a small websocket message waits for the client's delayed ACK."""
    sock = listen_socket("127.0.0.1", 0, 65536)
    port = sock.getsockname()[1]
    seen: dict = {}

    async def main():
        accepted = asyncio.Event()

        class Probe(asyncio.Protocol):
            def connection_made(self, transport):
                s = transport.get_extra_info("socket")
                seen["nodelay"] = s.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY)
                seen["sndbuf"] = s.getsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF)
                transport.close()
                accepted.set()

        server = await asyncio.get_running_loop().create_server(Probe, sock=sock)
        async with server:
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            await asyncio.wait_for(accepted.wait(), 10)
            writer.close()

    asyncio.run(main())
    assert seen["nodelay"] != 0, "TCP_NODELAY is off on accepted connections"
    # Linux reports twice the size asked for (bookkeeping overhead), never the autotuned megabytes.
    assert 65536 <= seen["sndbuf"] <= 2 * 65536
