"""uvicorn's websocket protocol, made quiet about one client fault: a text frame that is not UTF-8 is closed
with 1007 (uvicorn's own doing), and frames of that kind that arrive after the close has begun are dropped.

uvicorn tries to send a second close for each of them, which raises, and asyncio logs that as a fatal error
with two tracebacks per connection (a client that sends bad frames and then closes does it every time).
`flockcal serve` passes `websocket_protocol()` as uvicorn's `ws`.
"""

from __future__ import annotations


def websocket_protocol():
    """uvicorn's automatic choice, with the guard when it is the websockets sans-I/O protocol; else as it is."""
    from uvicorn.protocols.websockets.auto import AutoWebSocketsProtocol

    try:
        from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
        from websockets.protocol import State
    except ImportError:  # another implementation: nothing of this applies
        return AutoWebSocketsProtocol
    if AutoWebSocketsProtocol is not WebSocketsSansIOProtocol:
        return AutoWebSocketsProtocol

    class QuietWebSocketsProtocol(WebSocketsSansIOProtocol):
        def send_receive_event_to_app(self) -> None:
            if getattr(self, "curr_msg_data_type", None) == "text" and self.conn.state is not State.OPEN:
                try:
                    b"".join(self.frames).decode()
                except UnicodeDecodeError:  # the connection is closing already: nothing to tell anyone
                    self.frames = []
                    return
            super().send_receive_event_to_app()

    return QuietWebSocketsProtocol
