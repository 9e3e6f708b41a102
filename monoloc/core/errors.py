"""The one error hierarchy of monoloc.

Every part raises these (or children defined next to the code that raises them).
The HTTP API maps them to status codes in one handler; the CLI prints one line and
exits non-zero.
"""

from __future__ import annotations

from pathlib import Path


class MonolocError(Exception):
    """Base of every error monoloc raises on purpose."""

    http_status: int = 500


class InvalidInputError(MonolocError):
    """The caller gave something malformed: a bad file, shape, value or format."""

    http_status = 422


class NotFoundError(MonolocError):
    """A named thing (map, entry, job, file) does not exist."""

    http_status = 404


class ConflictError(MonolocError):
    """The request contradicts what is stored (duplicate name, wrong state)."""

    http_status = 409


class InputFileError(InvalidInputError):
    """A file is missing or malformed. The message starts with ``path:line:`` (line
    omitted when the whole file is at fault) so editors and people can jump to it."""

    def __init__(self, path: Path | str, message: str, line: int | None = None) -> None:
        self.path = Path(path)
        self.line = line
        where = f"{self.path}:{line}" if line is not None else f"{self.path}"
        super().__init__(f"{where}: {message}")
