"""The live service: FastAPI app, sessions, websocket, dashboard and SQLite persistence."""
