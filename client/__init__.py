"""monoloc client: the light on-vehicle library (numpy + httpx only).

Particle filter, motion and measurement models, planar geometry, and the API client.
Nothing here imports OpenCV, FAISS, FastAPI or SQLAlchemy.
"""
