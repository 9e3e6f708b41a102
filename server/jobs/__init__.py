"""Durable jobs: ingestion of uploaded runs, vocabulary changes, calibrations, each a row
of the ``jobs`` table that survives a crash and can be resumed.

One idea per module: ``store`` (the SQL of the jobs table and its state transitions),
``progress`` (throttled progress writes to a job's row), ``uploads`` (where a job's
uploaded run lives and how it is opened), ``params`` (a job's parameters: one model
per kind, checked at creation, read back from the row), ``context`` (what a handler gets),
``runner`` (the queue: a thread pool running queued jobs, cancel, stop), ``resume``
(which jobs may be re-queued), ``lifecycle`` (a job run in the foreground by a CLI
command), the kinds ``ingest``, ``vocabulary`` and ``calibration``, and ``handlers``
(which handler runs each kind).

Nothing is imported here so that ``import monoloc.server.jobs`` stays cheap.
"""
