"""The HTTP/WebSocket map server (FastAPI). Build it with ``server.api.app.create_app``."""
