"""A one-page look at a dataset written by ``monoloc sim generate``: its dataset.json
says which scenario wrote it, whose preview draws the page."""

from __future__ import annotations

import json
from pathlib import Path

from monoloc.core.errors import InvalidInputError, NotFoundError
from monoloc.sim.indoor.preview import write_indoor_preview
from monoloc.sim.urban.preview import write_urban_preview


def write_preview(dataset: Path, out: Path, per_run: int = 4) -> Path:
    """Write ``out`` (PNG) for the dataset at ``dataset``; returns ``out``."""
    dataset = Path(dataset)
    info_path = dataset / "dataset.json"
    if not info_path.exists():
        raise NotFoundError(f"{info_path} does not exist (not a sim dataset?)")
    try:
        info = json.loads(info_path.read_text())
    except ValueError as exc:
        raise InvalidInputError(f"{info_path}: not a valid dataset.json ({exc})") from exc
    if not isinstance(info, dict) or "sequences" not in info:
        raise InvalidInputError(f"{info_path}: not a valid dataset.json (no 'sequences')")
    if info.get("format") == "tum-rgbd":
        return write_indoor_preview(dataset, info, out, per_run)
    return write_urban_preview(dataset, info, out, per_run)
