"""The live service: FastAPI app, sessions, websocket, dashboard and SQLite persistence."""

from flockcal.lazy import public_api

# What a user of the service reaches for, each loaded on first use (tests/test_public_api.py resolves them).
__getattr__, __dir__, __all__ = public_api(__name__, {
    "Service": "flockcal.server.service",
    "Settings": "flockcal.server.settings",
    "create_app": "flockcal.server.app",
    "ServerError": "flockcal.server.errors",
})
