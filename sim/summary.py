"""What generating a dataset reports, whatever the scenario: one line per sequence."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class SequenceSummary:
    seq_id: str
    kind: str
    lighting: str
    frames: int
    length_m: float


@dataclass(frozen=True)
class DatasetSummary:
    root: Path
    sequences: list[SequenceSummary]
    seconds: float


def frames_per_second_note(summary: DatasetSummary) -> str:
    n = sum(s.frames for s in summary.sequences)
    return f"{n} frames in {summary.seconds:.1f} s ({n / max(summary.seconds, 1e-9):.1f} fps)"
