"""The Host-header allow-list: the service answers only to the names it is known by.

A web page that rebinds its own domain to 127.0.0.1 reaches a loopback service with its own name in
`Host`; refusing every name but loopback's (and the `--allow-host` ones) takes the API away from it.
"""

from __future__ import annotations

import ipaddress
import json

LOOPBACK_NAMES = ("localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback")


def host_name(header: str) -> str:
    """The name part of a Host header ('Example.org.:8750' → 'example.org', '[::1]:80' → '::1')."""
    header = header.strip().lower()
    if header.startswith("["):
        return header[1:].partition("]")[0]
    if header.count(":") > 1:  # a bare IPv6 address, no port
        return header
    return header.partition(":")[0].rstrip(".")


def _is_loopback_address(name: str) -> bool:
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


class HostPolicy:
    """Which Host names a request may carry: loopback names and addresses always, the address the
    service listens on when it is a specific one, and every `--allow-host` name ('*' allows any)."""

    def __init__(self, listen_host: str, allowed: tuple[str, ...] = ()):
        names = {host_name(h) for h in allowed if h.strip()}
        self.any = "*" in names
        listen = host_name(listen_host)
        try:
            if not ipaddress.ip_address(listen).is_unspecified:
                names.add(listen)
        except ValueError:
            names.add(listen)  # a host name given to --host is a name the service is reached by
        self.names = frozenset(names - {"*"})

    def allows(self, header: str | None) -> bool:
        if self.any:
            return True
        if not header:
            return False  # HTTP/1.1 requires Host; every browser and client sends one
        name = host_name(header)
        return name in LOOPBACK_NAMES or _is_loopback_address(name) or name in self.names


class HostCheck:
    """ASGI middleware: 400 (HTTP) or a refused handshake (websocket) for a Host not in the policy."""

    def __init__(self, app, policy: HostPolicy):
        self.app = app
        self.policy = policy

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        raw = dict(scope.get("headers") or []).get(b"host")
        header = raw.decode("latin-1") if raw is not None else None
        if self.policy.allows(header):
            return await self.app(scope, receive, send)
        name = host_name(header) if header else ""
        detail = (f"this service does not answer to the host name {name[:80]!r}; if that is how you reach it, "
                  f"start it with --allow-host {name[:80] or 'NAME'}") if name else \
            "the request has no Host header; send one"
        if scope["type"] == "websocket":
            # Before accept: uvicorn answers the handshake with 403 and nothing is streamed.
            await send({"type": "websocket.close", "code": 1008, "reason": "host not allowed"})
            return
        body = json.dumps({"detail": detail, "error": "host_not_allowed"}).encode()
        await send({"type": "http.response.start", "status": 400,
                    "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})
