"""What a job handler gets from the runner (:class:`JobContext`: its job, the database,
the registry, a stop flag, progress) and how it says it stopped early."""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from monoloc.server.jobs.progress import ProgressWriter
from monoloc.server.jobs.uploads import upload_dir_of
from monoloc.server.settings import Settings
from monoloc.server.storage.records import JobRecord


class JobInterruptedError(Exception):
    """Raised by a handler that stopped early because ``ctx.should_stop()`` said so."""


@dataclass
class JobContext:
    """What a handler gets: its job, the database, the registry, a stop flag, progress."""

    job: JobRecord
    sessions: sessionmaker[Session]
    registry: Any
    settings: Settings
    stop_event: threading.Event
    progress_interval_s: float = 0.5
    _writer: ProgressWriter = field(init=False)

    def __post_init__(self) -> None:
        self._writer = ProgressWriter(self.sessions, self.job.id, self.progress_interval_s)

    def should_stop(self) -> bool:
        return self.stop_event.is_set()

    def progress(self, fraction: float, message: str = "", *, force: bool = False) -> None:
        """Record ``fraction`` (clamped to 0..1) and ``message``, throttled unless forced."""
        self._writer.write(min(1.0, max(0.0, float(fraction))), message, force=force)

    def upload_dir(self) -> Path | None:
        """``data_dir/uploads/<job id>`` for jobs that came with an upload."""
        return upload_dir_of(self.job, self.settings)


JobHandler = Callable[[JobContext], Mapping[str, Any]]
