"""One query frame through the pipeline, shared by ``POST .../localize`` and the stream.

The request part (:class:`QueryOptions`: intrinsics, prior, k, seed) is validated on the
event loop; :func:`localize_encoded` (decode + pipeline) runs on the CPU pool.

Randomness (RANSAC): each frame gets its own ``np.random.Generator``. Its seed is the
request's ``seed`` when given (the same frame, seed and map version give the same
answer), otherwise a fresh draw from the server's ``SeedSequence`` (seeded by
``MONOLOC_LOCALIZE_SEED``, OS entropy when unset). The answer reports the seed used.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.prior import RetrievalPrior
from monoloc.server.api.convert import localize_response
from monoloc.server.api.deps import AppState
from monoloc.server.api.limits import ImageInfo, check_image, decode_gray
from monoloc.server.api.schemas_localize import LocalizeResponse
from monoloc.server.localize import LocalizeConfig

MAX_K = 100


@dataclass(frozen=True)
class QueryOptions:
    """Optional inputs of one query: fx, fy, cx, cy (all or none), a prior, k, seed."""

    focal: tuple[float, float, float, float] | None = None
    prior: RetrievalPrior | None = None
    k: int | None = None
    seed: int | None = None


def _finite(name: str, value: Any) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name} must be a number, got {value!r}") from exc
    if not math.isfinite(number):
        raise InvalidInputError(f"{name} must be finite, got {value!r}")
    return number


def parse_options(values: dict[str, Any]) -> QueryOptions:
    """QueryOptions from flat fields (fx, fy, cx, cy, prior_x_m, prior_y_m,
    prior_radius_m, prior_yaw_rad, prior_yaw_tolerance_rad, k, seed); None = absent."""
    present = {k: v for k, v in values.items() if v is not None and v != ""}
    focal_names = ("fx", "fy", "cx", "cy")
    given = [n for n in focal_names if n in present]
    focal = None
    if given:
        if len(given) != 4:
            raise InvalidInputError(f"give all of fx, fy, cx, cy or none (got only {given})")
        fx, fy, cx, cy = (_finite(n, present[n]) for n in focal_names)
        if fx <= 0 or fy <= 0:
            raise InvalidInputError(f"fx and fy must be positive, got {fx}, {fy}")
        focal = (fx, fy, cx, cy)
    prior_names = ("prior_x_m", "prior_y_m", "prior_radius_m")
    yaw_names = ("prior_yaw_rad", "prior_yaw_tolerance_rad")
    got_pos = [n for n in prior_names if n in present]
    got_yaw = [n for n in yaw_names if n in present]
    prior = None
    if got_pos or got_yaw:
        if len(got_pos) != 3:
            raise InvalidInputError(
                f"a prior needs prior_x_m, prior_y_m and prior_radius_m (got {got_pos + got_yaw})"
            )
        if len(got_yaw) == 1:
            raise InvalidInputError("give prior_yaw_rad and prior_yaw_tolerance_rad together")
        x, y, r = (_finite(n, present[n]) for n in prior_names)
        if r <= 0:
            raise InvalidInputError(f"prior_radius_m must be positive, got {r}")
        yaw = _finite(yaw_names[0], present[yaw_names[0]]) if got_yaw else None
        tol = _finite(yaw_names[1], present[yaw_names[1]]) if got_yaw else None
        if tol is not None and tol <= 0:
            raise InvalidInputError(f"prior_yaw_tolerance_rad must be positive, got {tol}")
        prior = RetrievalPrior(x, y, r, yaw, tol)
    k = None
    if "k" in present:
        k_value = _finite("k", present["k"])
        if not k_value.is_integer() or not 1 <= k_value <= MAX_K:
            raise InvalidInputError(f"k must be an integer in 1..{MAX_K}, got {present['k']!r}")
        k = int(k_value)
    seed = None
    if "seed" in present:
        seed_value = _finite("seed", present["seed"])
        if not seed_value.is_integer() or not 0 <= seed_value < 2**63:
            raise InvalidInputError(
                f"seed must be an integer in [0, 2^63), got {present['seed']!r}"
            )
        seed = int(seed_value)
    return QueryOptions(focal, prior, k, seed)


def _intrinsics(
    state: AppState, map_id: int, info: ImageInfo, options: QueryOptions
) -> CameraIntrinsics | None:
    if options.focal is not None:
        fx, fy, cx, cy = options.focal
        return CameraIntrinsics(fx, fy, cx, cy, info.width_px, info.height_px)
    camera = state.registry.get(map_id).record.camera
    if (camera.width_px, camera.height_px) != (info.width_px, info.height_px):
        raise InvalidInputError(
            f"the image is {info.width_px}x{info.height_px} but the map's camera is "
            f"{camera.width_px}x{camera.height_px}: send fx, fy, cx, cy for this image"
        )
    return None


def localize_encoded(
    state: AppState, map_id: int, data: bytes, info: ImageInfo, options: QueryOptions
) -> LocalizeResponse:
    """Decode + localize one checked image (blocking: call through ``state.run_cpu``)."""
    start = time.perf_counter()
    intrinsics = _intrinsics(state, map_id, info, options)
    image = decode_gray(data, info, "image")
    decode_ms = (time.perf_counter() - start) * 1e3
    seed = options.seed if options.seed is not None else state.next_seed()
    result, version = state.registry.localize(
        map_id,
        image,
        LocalizeConfig(pipeline=state.settings.localize_pipeline),
        np.random.default_rng(seed),
        intrinsics,
        options.prior,
        options.k,
    )
    timings = {"decode": decode_ms, **result.timings_ms}
    timings["total"] = result.timings_ms.get("total", 0.0) + decode_ms
    state.metrics.observe_localize(timings)
    return localize_response(map_id, version, result, timings, seed)


async def localize_bytes(
    state: AppState, map_id: int, data: bytes, options: QueryOptions
) -> LocalizeResponse:
    """Check the image header on the loop (cheap), run the rest on the CPU pool."""
    info = check_image(data, "image", state.settings.max_image_pixels)
    return await state.run_cpu(localize_encoded, state, map_id, data, info, options)
