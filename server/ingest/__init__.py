"""Ingestion of recordings into maps: the recordings as sources (``sources``), the pipeline
(``pipeline.ingest_run``), single images (``single``), vocabularies (``vocab``) and
the typed operations behind the CLI (``manage``, ``report``).

Nothing is imported here so that ``import monoloc.server.ingest`` stays cheap.
"""
