"""The HTTP/WebSocket map server (FastAPI). Build it with ``monoloc.server.api.app.create_app``."""
