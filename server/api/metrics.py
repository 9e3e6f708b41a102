"""Prometheus metrics, exposed at /metrics in the text exposition format (version 0.0.4).

Written here rather than with prometheus_client: four histograms and a few gauges do not
justify a dependency, and per-app instances keep tests independent.

* ``monoloc_http_request_duration_seconds{method, route, status}``: histogram of request
  latency per route template (``/v1/maps/{map_id}/localize``), from
  :class:`RequestMetricsMiddleware`.
* ``monoloc_localize_stage_duration_seconds{stage}``: histogram of the localization
  stages (decode, features, vlad, retrieval, lookup, matching, pnp, total).
* ``monoloc_stream_frames_total{outcome}``: WebSocket frames answered, dropped, failed.
* ``monoloc_admission_shed_total{lane}``, ``monoloc_admission_expired_total{lane, reason}``:
  requests turned away by admission control (``server/api/admission.py``); its queue
  depths are gauges read at scrape time.
* ``monoloc_map_entries{map_id, map}``, ``monoloc_jobs{kind, state}`` and
  ``monoloc_maps_loaded``: gauges read from the database / registry at scrape time.
"""

from __future__ import annotations

import bisect
import threading
import time
from collections import defaultdict
from collections.abc import Iterable, Mapping

from starlette.types import ASGIApp, Message, Receive, Scope, Send

LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)


def _escape(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _labels(names: tuple[str, ...], values: tuple[str, ...], extra: str = "") -> str:
    parts = [f'{n}="{_escape(v)}"' for n, v in zip(names, values, strict=True)]
    if extra:
        parts.append(extra)
    return "{" + ",".join(parts) + "}" if parts else ""


def _number(value: float) -> str:
    if value == float("inf"):
        return "+Inf"
    return repr(float(value)) if not float(value).is_integer() else str(int(value))


class Histogram:
    """A labelled histogram with fixed buckets; thread-safe."""

    def __init__(
        self,
        name: str,
        help_text: str,
        label_names: tuple[str, ...],
        buckets: tuple[float, ...] = LATENCY_BUCKETS_S,
    ) -> None:
        self.name, self.help, self.label_names, self.buckets = name, help_text, label_names, buckets
        self._series: dict[tuple[str, ...], list[float]] = {}
        self._lock = threading.Lock()

    def observe(self, value: float, *labels: str) -> None:
        with self._lock:
            series = self._series.get(labels)
            if series is None:
                # counts per bucket (non-cumulative), then +Inf count, sum
                series = self._series[labels] = [0.0] * (len(self.buckets) + 2)
            series[bisect.bisect_left(self.buckets, value)] += 1
            series[-1] += value

    def render(self) -> Iterable[str]:
        yield f"# HELP {self.name} {self.help}"
        yield f"# TYPE {self.name} histogram"
        with self._lock:
            items = sorted((k, list(v)) for k, v in self._series.items())
        for labels, series in items:
            cumulative = 0.0
            for bound, count in zip((*self.buckets, float("inf")), series[:-1], strict=True):
                cumulative += count
                le = f'le="{_number(bound)}"'
                bucket_labels = _labels(self.label_names, labels, le)
                yield f"{self.name}_bucket{bucket_labels} {_number(cumulative)}"
            yield f"{self.name}_sum{_labels(self.label_names, labels)} {series[-1]!r}"
            yield f"{self.name}_count{_labels(self.label_names, labels)} {_number(cumulative)}"


class Counter:
    """A labelled monotonic counter; thread-safe."""

    def __init__(self, name: str, help_text: str, label_names: tuple[str, ...]) -> None:
        self.name, self.help, self.label_names = name, help_text, label_names
        self._values: dict[tuple[str, ...], float] = defaultdict(float)
        self._lock = threading.Lock()

    def inc(self, *labels: str, amount: float = 1.0) -> None:
        with self._lock:
            self._values[labels] += amount

    def value(self, *labels: str) -> float:
        with self._lock:
            return self._values.get(labels, 0.0)

    def render(self) -> Iterable[str]:
        yield f"# HELP {self.name} {self.help}"
        yield f"# TYPE {self.name} counter"
        with self._lock:
            items = sorted(self._values.items())
        for labels, value in items:
            yield f"{self.name}{_labels(self.label_names, labels)} {_number(value)}"


def render_gauge(
    name: str, help_text: str, label_names: tuple[str, ...], values: Mapping[tuple[str, ...], float]
) -> Iterable[str]:
    yield f"# HELP {name} {help_text}"
    yield f"# TYPE {name} gauge"
    for labels, value in sorted(values.items()):
        yield f"{name}{_labels(label_names, labels)} {_number(value)}"


class Metrics:
    """The metrics of one app instance."""

    def __init__(self) -> None:
        self.requests = Histogram(
            "monoloc_http_request_duration_seconds",
            "HTTP request latency by route template.",
            ("method", "route", "status"),
        )
        self.localize_stages = Histogram(
            "monoloc_localize_stage_duration_seconds",
            "Time spent in each localization stage (decode included).",
            ("stage",),
        )
        self.stream_frames = Counter(
            "monoloc_stream_frames_total",
            "WebSocket stream frames by outcome (answered, dropped, error).",
            ("outcome",),
        )
        self.admission_shed = Counter(
            "monoloc_admission_shed_total",
            "Requests answered 503 at once because their lane was full (nothing computed).",
            ("lane",),
        )
        self.admission_expired = Counter(
            "monoloc_admission_expired_total",
            "Admitted requests dropped before computing: deadline passed or client gone.",
            ("lane", "reason"),
        )

    def observe_localize(self, timings_ms: Mapping[str, float]) -> None:
        for stage, ms in timings_ms.items():
            self.localize_stages.observe(ms / 1e3, stage)


class RequestMetricsMiddleware:
    """Times every HTTP request and files it under its route template (after routing,
    ``scope["route"]`` names it; unmatched paths count as ``<unmatched>``)."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

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
