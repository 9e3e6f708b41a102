"""monoloc client: the light on-vehicle library (numpy + httpx only).

Particle filter and motion model, the vehicle's loop (tracking) fed by a Localizer (HTTP
or WebSocket stream here; in process: monoloc.server.localize.in_process), and the API client.
Nothing here imports OpenCV, FAISS, FastAPI or SQLAlchemy.
"""
