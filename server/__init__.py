"""The monoloc map server: vision core, map database, retrieval index and HTTP API."""
