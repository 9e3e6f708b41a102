"""Prometheus metrics through prometheus_client, exposed at /metrics.

One :class:`Metrics` per app, on its own registry (apps in one process, as in the tests,
stay independent). Under ``monoloc serve --workers N`` the workers are separate
processes: ``serve`` points ``PROMETHEUS_MULTIPROC_DIR`` at an emptied directory before
they start, each worker's values go to files there, and a scrape answered by any worker
aggregates all of them (prometheus_client's multiprocess mode). Separate replicas
(containers) are separate scrape targets.

* ``monoloc_http_request_duration_seconds{method, route, status}``: histogram of request
  latency per route template (``/v1/maps/{map_id}/localize``), from
  :class:`RequestMetricsMiddleware`.
* ``monoloc_localize_stage_duration_seconds{stage}``: histogram of the localization
  stages (decode, features, vlad, retrieval, lookup, matching, pnp, total).
* ``monoloc_localize_frames_total{map_id, outcome}``: frames (HTTP and stream) by
  outcome: ``hypotheses`` (answered with at least one), ``no_hypothesis``
  (answered with none), ``shed`` (refused uncomputed: lane full, deadline, client gone,
  stale replica), ``failed`` (a bad frame or a server error).
* ``monoloc_stream_frames_total{outcome}``: WebSocket frames answered, dropped, failed.
* ``monoloc_admission_shed_total{lane}``, ``monoloc_admission_expired_total{lane, reason}``:
  requests turned away by admission control (``server/api/admission.py``);
  ``monoloc_admission_{waiting,running,capacity}{lane}``: its lanes, summed over the
  live worker processes.
* ``monoloc_maps_loaded``: maps whose index is in memory (per worker process, ``pid``
  label, in multiprocess mode); ``monoloc_map_entries{map_id, map}`` and
  ``monoloc_jobs{kind, state}``: read from the database at scrape time.
"""

from __future__ import annotations

import os
import re
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

import prometheus_client
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client import Counter as _Counter
from prometheus_client import Gauge as _Gauge
from prometheus_client import Histogram as _Histogram
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.multiprocess import MultiProcessCollector, mark_process_dead
from starlette.types import ASGIApp, Message, Receive, Scope, Send

LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
MULTIPROC_ENV = "PROMETHEUS_MULTIPROC_DIR"
CONTENT_TYPE = prometheus_client.CONTENT_TYPE_LATEST
ADMISSION_GAUGES = ("waiting", "running", "capacity")
FRAME_OUTCOMES = ("hypotheses", "no_hypothesis", "shed", "failed")
_LOCALIZE_PATH = re.compile(r"^/v1/maps/(\d+)/localize$")


def multiprocess_dir() -> Path | None:
    """The directory of multiprocess mode, None in a single process."""
    value = os.environ.get(MULTIPROC_ENV)
    return Path(value) if value else None


def prepare_multiprocess_dir(path: Path) -> None:
    """Make ``path`` the empty directory of multiprocess mode (``serve --workers N``,
    before the workers start): files of an earlier run would be counted again."""
    path.mkdir(parents=True, exist_ok=True)
    for stale in path.glob("*.db"):
        stale.unlink()
    os.environ[MULTIPROC_ENV] = str(path)


def _render(collector: object) -> list[str]:
    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)  # type: ignore[arg-type]
    return generate_latest(registry).decode().splitlines()


class Histogram:
    """A labelled histogram; labels are given positionally, in ``label_names`` order."""

    def __init__(
        self,
        name: str,
        help_text: str,
        label_names: tuple[str, ...],
        registry: CollectorRegistry,
        buckets: tuple[float, ...] = LATENCY_BUCKETS_S,
    ) -> None:
        self.name, self.label_names = name, label_names
        self._metric = _Histogram(name, help_text, label_names, registry=registry, buckets=buckets)

    def observe(self, value: float, *labels: str) -> None:
        self._metric.labels(*labels).observe(value)

    def render(self) -> Iterable[str]:
        """This process's series in the text format (HELP, TYPE, then samples)."""
        return _render(self._metric)


class Counter:
    """A labelled monotonic counter; ``name`` without prometheus_client's ``_total``."""

    def __init__(
        self, name: str, help_text: str, label_names: tuple[str, ...], registry: CollectorRegistry
    ) -> None:
        self.name, self.label_names = name, label_names
        self._metric = _Counter(name, help_text, label_names, registry=registry)

    def inc(self, *labels: str, amount: float = 1.0) -> None:
        self._metric.labels(*labels).inc(amount)

    def value(self, *labels: str) -> float:
        """This process's count for ``labels`` (0 when never counted)."""
        wanted = dict(zip(self.label_names, labels, strict=True))
        for family in self._metric.collect():
            for sample in family.samples:
                if sample.name.endswith("_total") and sample.labels == wanted:
                    return sample.value
        return 0.0

    def render(self) -> Iterable[str]:
        return _render(self._metric)


class Metrics:
    """The metrics of one app instance."""

    def __init__(self) -> None:
        prometheus_client.disable_created_metrics()  # no *_created series: noise here
        self.registry = registry = CollectorRegistry(auto_describe=True)
        self.requests = Histogram(
            "monoloc_http_request_duration_seconds",
            "HTTP request latency by route template.",
            ("method", "route", "status"),
            registry,
        )
        self.localize_stages = Histogram(
            "monoloc_localize_stage_duration_seconds",
            "Time spent in each localization stage (decode included).",
            ("stage",),
            registry,
        )
        self.localize_frames = Counter(
            "monoloc_localize_frames",
            "Frames (HTTP and stream) by map and outcome: hypotheses, no_hypothesis, "
            "shed (refused uncomputed), failed.",
            ("map_id", "outcome"),
            registry,
        )
        self.stream_frames = Counter(
            "monoloc_stream_frames",
            "WebSocket stream frames by outcome (answered, dropped, error).",
            ("outcome",),
            registry,
        )
        self.admission_shed = Counter(
            "monoloc_admission_shed",
            "Requests answered 503 at once because their lane was full (nothing computed).",
            ("lane",),
            registry,
        )
        self.admission_expired = Counter(
            "monoloc_admission_expired",
            "Admitted requests dropped before computing: deadline passed or client gone.",
            ("lane", "reason"),
            registry,
        )
        self.admission_lanes = {
            kind: _Gauge(
                f"monoloc_admission_{kind}",
                f"Requests per admission lane: {kind}.",
                ("lane",),
                registry=registry,
                multiprocess_mode="livesum",
            )
            for kind in ADMISSION_GAUGES
        }
        self.maps_loaded = _Gauge(
            "monoloc_maps_loaded",
            "Maps whose index is in memory.",
            registry=registry,
            multiprocess_mode="liveall",
        )

    def observe_localize(self, timings_ms: Mapping[str, float]) -> None:
        for stage, ms in timings_ms.items():
            self.localize_stages.observe(ms / 1e3, stage)

    def count_frame(self, map_id: int | str, outcome: str) -> None:
        self.localize_frames.inc(str(map_id), outcome)

    def count_stream_answer(self, map_id: int, body: Mapping[str, object]) -> None:
        """A stream frame refused or failed (its answer's JSON); answered ones are
        counted where they are localized."""
        if body.get("dropped"):
            if body.get("reason") in ("overloaded", "deadline"):
                self.count_frame(map_id, "shed")
        elif "error" in body:
            self.count_frame(map_id, "failed")

    def set_process_gauges(
        self, admission: Mapping[str, Mapping[tuple[str, ...], float]], maps_loaded: int
    ) -> None:
        """This process's admission lanes (``Admission.gauges()``) and loaded maps."""
        for kind, values in admission.items():
            gauge = self.admission_lanes.get(kind)
            for labels, value in values.items():
                if gauge is not None:
                    gauge.labels(*labels).set(value)
        self.maps_loaded.set(maps_loaded)

    def exposition(self, scrape_time: object | None = None) -> bytes:
        """The text format: every worker's values in multiprocess mode, else this app's;
        ``scrape_time``: a collector of values read now (the database's gauges)."""
        if multiprocess_dir() is not None:
            registry = CollectorRegistry(auto_describe=False)
            MultiProcessCollector(registry)
        else:
            registry = self.registry
        text = generate_latest(registry)
        if scrape_time is not None:
            text += "\n".join(_render(scrape_time)).encode() + b"\n"
        return text


class ScrapeGauges:
    """Gauges computed at scrape time: ``families`` yields (name, help, label names,
    values by label tuple)."""

    def __init__(
        self,
        families: Iterable[tuple[str, str, tuple[str, ...], Mapping[tuple[str, ...], float]]],
    ) -> None:
        self._families = list(families)

    def collect(self):
        for name, help_text, label_names, values in self._families:
            family = GaugeMetricFamily(name, help_text, labels=list(label_names))
            for labels, value in sorted(values.items()):
                family.add_metric(list(labels), value)
            yield family


class GaugeRefresher:
    """In multiprocess mode, writes this process's gauges every ``period_s`` so that a
    scrape answered by another worker sees them; the files go when the process stops."""

    def __init__(self, refresh: Callable[[], None], period_s: float = 1.0) -> None:
        self._refresh, self._period_s = refresh, period_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._refresh()
        if multiprocess_dir() is None:
            return
        self._thread = threading.Thread(target=self._run, name="metrics-gauges", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            try:
                self._refresh()
            except Exception:  # noqa: BLE001 - the next tick tries again
                time.sleep(self._period_s)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        if multiprocess_dir() is not None:
            mark_process_dead(os.getpid())


class RequestMetricsMiddleware:
    """Times every HTTP request and files it under its route template (after routing,
    ``scope["route"]`` names it; unmatched paths count as ``<unmatched>``). A frame
    refused before its route ran (shed by admission control, a timed-out body) is
    counted in ``monoloc_localize_frames_total`` here; one the route answered, there."""

    def __init__(
        self, app: ASGIApp, metrics: Metrics, known_map: Callable[[int], bool] | None = None
    ) -> None:
        self.app = app
        self.metrics = metrics
        self.known_map = known_map

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            route = getattr(scope.get("route"), "path", None) or "<unmatched>"
            self.metrics.requests.observe(
                time.perf_counter() - start, scope.get("method", ""), route, str(status)
            )
            if scope.get("method") == "POST" and status not in (200, 401, 403, 404):
                self._refused_frame(scope, status)

    def _refused_frame(self, scope: Scope, status: int) -> None:
        found = _LOCALIZE_PATH.match(scope.get("path", ""))
        if found is None:
            return
        map_id = int(found.group(1))
        # an unauthenticated flood of made-up map ids must not make a series each
        label = str(map_id) if self.known_map is None or self.known_map(map_id) else "other"
        outcome = "shed" if status == 503 else "failed"
        self.metrics.count_frame(label, outcome)
