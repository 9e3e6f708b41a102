"""What the text formats share: a source is a path or an open text handle; rows of
numbers are read with the file and the line named on any error."""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import TextIO

import numpy as np

from monoloc.core.errors import InputFileError

Source = str | os.PathLike | TextIO


def read_lines(source: Source, what: str) -> tuple[Path, list[str]]:
    """(the name errors give, the lines) of a path or an open text handle."""
    if isinstance(source, str | os.PathLike):
        path = Path(source)
        try:
            return path, path.read_text().splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            raise InputFileError(path, f"cannot read {what}: {exc}") from exc
    return Path(getattr(source, "name", "<stream>")), source.read().splitlines()


def data_lines(lines: list[str]) -> Iterator[tuple[int, list[str]]]:
    """(1-based line number, whitespace-separated fields) of every line that is neither
    blank nor a '#' comment."""
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            yield number, stripped.split()


def finite_numbers(path: Path, number: int, fields: list[str], what: str) -> list[float]:
    """The fields as floats; InputFileError at ``path:number`` if one is not a finite
    number."""
    values = []
    for field in fields:
        try:
            values.append(float(field))
        except ValueError as exc:
            raise InputFileError(path, f"not a number: {field!r} in {what}", number) from exc
    if not all(math.isfinite(v) for v in values):
        raise InputFileError(path, f"{what} contains NaN or infinite values", number)
    return values


def number_rows(source: Source, n_columns: int, what: str) -> tuple[Path, np.ndarray, list[int]]:
    """Rows of ``n_columns`` finite numbers: (name, (N, n_columns) float64, the line
    number of each row). Blank lines and '#' comments are skipped."""
    path, lines = read_lines(source, what)
    rows, numbers = [], []
    for number, fields in data_lines(lines):
        if len(fields) != n_columns:
            raise InputFileError(
                path, f"{what} has {len(fields)} values, expected {n_columns}", number
            )
        rows.append(finite_numbers(path, number, fields, what))
        numbers.append(number)
    return path, np.asarray(rows, dtype=np.float64).reshape(-1, n_columns), numbers
