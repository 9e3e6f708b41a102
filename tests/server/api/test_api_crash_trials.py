"""Crash trials against a real server process (``bench.lab.crash_trials``): SIGKILL during
ingestion, during entry adds and deletes, and around the index file write; after the
restart nothing acknowledged is lost, nothing is duplicated, and the served index equals
the database. One trial per kind here; ``bench/crash.py`` runs 50."""

from __future__ import annotations

import numpy as np
import pytest
from api_helpers import camera_of

from bench.lab.crash_trials import KINDS, TrialDataset, run_trial


@pytest.mark.parametrize("kind", KINDS)
def test_sigkill_loses_nothing_acknowledged(sim_dataset, tmp_path, kind):
    dataset = TrialDataset(sim_dataset, "00", camera_of(sim_dataset))
    rng = np.random.default_rng(KINDS.index(kind))
    result = run_trial(kind, dataset, tmp_path / kind, rng)
    assert result.acknowledged > 0, result
    assert result.ok, result
