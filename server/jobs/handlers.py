"""Which handler the job runner calls for each job kind."""

from __future__ import annotations

from monoloc.server.jobs import calibration, ingest, vocabulary
from monoloc.server.jobs.context import JobHandler

HANDLERS: dict[str, JobHandler] = {
    ingest.JOB_KIND: ingest.run_ingest,
    vocabulary.JOB_KIND: vocabulary.run_vocabulary,
    calibration.JOB_KIND: calibration.run_calibration,
}
