"""`monoloc serve --workers 2`: /metrics, whichever worker answers it, counts every
worker's requests (prometheus_client's multiprocess mode, its directory emptied at start
so a previous run's values are not counted again)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import httpx
from api_helpers import free_port
from prometheus_client.mmap_dict import MmapedDict, mmap_key
from prometheus_client.parser import text_string_to_metric_families

from monoloc.client.api import ServerError, wait_until_ready

REQUESTS = 40
STALE = 1000.0


def _samples(text: str) -> list:
    return [s for family in text_string_to_metric_families(text) for s in family.samples]


def _healthz_count(samples) -> float:
    return sum(
        s.value
        for s in samples
        if s.name == "monoloc_http_request_duration_seconds_count"
        and s.labels.get("route") == "/healthz"
    )


def _leave_stale_values(directory) -> None:
    """What a previous run's worker leaves behind: a counter file with 1000 frames."""
    directory.mkdir(parents=True)
    stale = MmapedDict(str(directory / "counter_999999.db"))
    key = mmap_key(
        "monoloc_stream_frames", "monoloc_stream_frames_total", ["outcome"], ["answered"], "h"
    )
    stale.write_value(key, STALE, 0.0)
    stale.close()


def test_metrics_sum_every_worker_and_forget_the_previous_run(tmp_path):
    port = free_port()
    multiproc = tmp_path / "prometheus"
    _leave_stale_values(multiproc)
    env = {k: v for k, v in os.environ.items() if not k.startswith("MONOLOC_")}
    env.update(
        MONOLOC_METRICS_PUBLIC="true",
        MONOLOC_WORKER_THREADS="1",
        MONOLOC_JOB_THREADS="1",
        PROMETHEUS_MULTIPROC_DIR=str(multiproc),
    )
    cmd = [sys.executable, "-m", "monoloc.cli", "serve", "--workers", "2", "--port", str(port)]
    cmd += ["--host", "127.0.0.1", "--data-dir", str(tmp_path / "data"), "--log-level", "warning"]
    log = tmp_path / "serve.log"
    with open(log, "wb") as out:
        process = subprocess.Popen(cmd, env=env, stdout=out, stderr=out)
    url = f"http://127.0.0.1:{port}"
    try:
        try:
            wait_until_ready(url, 180, process, poll_s=0.1)
        except ServerError as exc:
            raise AssertionError(f"{exc}: {log.read_text()[-3000:]}") from exc
        # both workers up: each has written its gauge of loaded maps (a pid label each)
        deadline = time.monotonic() + 60
        while True:
            samples = _samples(httpx.get(f"{url}/metrics", timeout=10).text)
            pids = {s.labels["pid"] for s in samples if s.name == "monoloc_maps_loaded"}
            if len(pids) == 2:
                break
            assert time.monotonic() < deadline, (pids, log.read_text()[-3000:])
            time.sleep(0.2)
        before = _healthz_count(samples)
        for _ in range(REQUESTS):  # a connection each: the kernel spreads them
            assert httpx.get(f"{url}/healthz", timeout=10).status_code == 200
        for _ in range(6):  # whichever worker answers, the same total
            samples = _samples(httpx.get(f"{url}/metrics", timeout=10).text)
            assert _healthz_count(samples) - before == REQUESTS
            stream = [s for s in samples if s.name == "monoloc_stream_frames_total"]
            assert all(s.value != STALE for s in stream), stream
    finally:
        process.terminate()
        try:
            process.wait(60)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    assert not (multiproc / "counter_999999.db").exists()
