"""Where a vehicle's hypotheses come from: one ``Localizer`` protocol, several places.

``localize(image, prior, k)`` answers one frame with the server's pose hypotheses
(docs/method.md section 6) as a :class:`LocalizeAnswer`. Remote implementations live here:
:class:`HttpLocalizer` (one ``POST /v1/maps/{id}/localize`` per frame) and
:class:`StreamLocalizer` (one frame at a time over the map's WebSocket stream). The
in-process one, the server's pipeline called directly, is
``monoloc.server.localize.in_process.InProcessLocalizer`` (the client does not import the server).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from monoloc.client.api import (
    FrameStream,
    LocalizeAnswer,
    MonolocClient,
    ServerError,
    jittered_wait_s,
)
from monoloc.core.camera import CameraIntrinsics
from monoloc.core.measurement import Hypotheses
from monoloc.core.prior import RetrievalPrior


class Localizer(Protocol):
    """Answers one frame: encoded PNG/JPEG bytes (remote), or also a grayscale (H, W)
    uint8 array (in process). ``prior``: restrict retrieval to it, None for the whole map;
    ``k``: entries to retrieve, None for the server's default. A frame the localizer
    dropped or could not process comes back without hypotheses (``dropped`` / ``error``)."""

    def localize(
        self, image, prior: RetrievalPrior | None = None, k: int | None = None
    ) -> LocalizeAnswer: ...


@dataclass
class ShedCounts:
    """What happened to the frames an :class:`HttpLocalizer` was given."""

    sent: int = 0  # requests made
    answered: int = 0  # answered with hypotheses (possibly none)
    shed: int = 0  # answered 503: the server was at capacity or the deadline passed
    held: int = 0  # not sent: inside the server's Retry-After window after a shed frame


class FrameHold:
    """Which frames a vehicle sends after a shed one: it comes back on the frame nearest
    the return the server asked for (``Retry-After-Ms`` from the shed frame's send time,
    lengthened by up to ``RETRY_JITTER`` drawn from ``rng``), not the first one after it.

    Why: a vehicle can only come back on a frame, and waiting for the first frame after
    the return rounds every wait up to whole frame periods: a drain time a little over
    one period cost a whole frame more per shed, frames the lane had room for
    (docs/notebook/fleet-and-load.md, 2026-12-02). The nearest frame is at most half a
    period early, against a wait that is the server's whole lane draining while a place
    frees every service slot. The period is the interval between the last two frames."""

    def __init__(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self._return_s = -math.inf
        self._last_frame_s: float | None = None
        self._period_s = 0.0

    def send(self, now_s: float) -> bool:
        """Whether the frame taken at ``now_s`` (s, the vehicle's clock) is sent; call it
        once per frame, sent or not."""
        if self._last_frame_s is not None and now_s > self._last_frame_s:
            self._period_s = now_s - self._last_frame_s
        self._last_frame_s = now_s
        # held only if the next frame is nearer the return than this one
        return now_s >= self._return_s - 0.5 * self._period_s

    def shed(self, sent_s: float, wait_s: float) -> None:
        """The frame sent at ``sent_s`` was shed with a wait of ``wait_s`` (s)."""
        self._return_s = max(self._return_s, sent_s + jittered_wait_s(wait_s, self._rng))


class HttpLocalizer:
    """One HTTP request per frame against map ``map_id``.

    A frame is worth nothing once the next one is taken, so it is sent once (no retry). A
    frame the server sheds (503) comes back as a dropped answer (the filter predicts only),
    and the frames inside the server's ``Retry-After`` window are not sent at all (dropped
    too): an overloaded server is given the time it asked for, up to a quarter more
    (``RETRY_JITTER``, drawn from ``rng``; pass one seeded per vehicle for a reproducible
    drive) so that vehicles told the same wait do not all come back in the same
    millisecond, and the vehicle comes back on the frame nearest that time
    (:class:`FrameHold`). ``counts`` keeps the tally. ``deadline_ms`` (X-Request-Deadline-Ms) tells
    the server when an answer is no longer worth computing; ``intrinsics``: the camera that
    took the frames, or ``camera_id`` its registered id (neither: the map's). Other errors
    raise (ServerError)."""

    def __init__(
        self,
        client: MonolocClient,
        map_id: int,
        deadline_ms: int | None = None,
        clock: Callable[[], float] = time.monotonic,
        intrinsics: CameraIntrinsics | None = None,
        camera_id: int | None = None,
        rng: np.random.Generator | None = None,
    ) -> None:
        self.client = client
        self.map_id = map_id
        self.deadline_ms = deadline_ms
        self.intrinsics = intrinsics
        self.camera_id = camera_id
        self.counts = ShedCounts()
        self._clock = clock
        self._hold = FrameHold(np.random.default_rng() if rng is None else rng)

    def localize(
        self, image: bytes, prior: RetrievalPrior | None = None, k: int | None = None
    ) -> LocalizeAnswer:
        now_s = self._clock()
        if not self._hold.send(now_s):
            self.counts.held += 1
            return _dropped("held")
        self.counts.sent += 1
        try:
            answer = self.client.localize(
                self.map_id,
                image,
                prior,
                k,
                retries=0,
                deadline_ms=self.deadline_ms,
                intrinsics=self.intrinsics,
                camera_id=self.camera_id,
            )
        except ServerError as exc:
            if exc.status_code != 503:
                raise
            self.counts.shed += 1
            self._hold.shed(now_s, exc.retry_after_s or 0.0)
            return _dropped("shed")
        self.counts.answered += 1
        return answer


def _dropped(reason: str) -> LocalizeAnswer:
    return LocalizeAnswer(
        Hypotheses.empty(), None, {}, {"dropped": True, "reason": reason}, dropped=True
    )


def check_answer_seq(answer: dict, expected: int) -> int:
    """The frame a stream answer belongs to; the stream answers in order, so it must be
    ``expected`` (ServerError otherwise)."""
    seq = answer.get("seq")
    if seq != expected:
        raise ServerError(
            f"the stream answered frame {seq} when frame {expected} was due: {str(answer)[:200]}"
        )
    return expected


class StreamLocalizer:
    """One frame at a time over an open stream: send frame ``seq`` (0, 1, ...), wait for
    its answer. The frame's time ``t`` is ``timestamps_s[seq]`` when given, else seconds
    since the first frame. A dropped or failed frame is an answer without hypotheses."""

    def __init__(
        self,
        stream: FrameStream,
        timestamps_s: Sequence[float] | None = None,
        intrinsics: CameraIntrinsics | None = None,
        camera_id: int | None = None,
    ) -> None:
        self.stream = stream
        self.timestamps_s = timestamps_s
        self.intrinsics = intrinsics
        self.camera_id = camera_id
        self.seq = 0
        self._t0: float | None = None

    def localize(
        self, image: bytes, prior: RetrievalPrior | None = None, k: int | None = None
    ) -> LocalizeAnswer:
        seq = self.seq
        if self.timestamps_s is not None:
            t_s = float(self.timestamps_s[seq])
        else:
            self._t0 = time.perf_counter() if self._t0 is None else self._t0
            t_s = time.perf_counter() - self._t0
        self.stream.send(
            seq, t_s, image, prior, k, intrinsics=self.intrinsics, camera_id=self.camera_id
        )
        self.seq += 1
        answer = self.stream.receive()
        check_answer_seq(answer, seq)
        return LocalizeAnswer.from_stream(answer)
