"""One query frame through the pipeline, shared by ``POST .../localize`` and the stream.

The request part (``LocalizeOptions``: intrinsics, prior, k, seed) is validated on the
event loop; :func:`localize_encoded` (decode + pipeline) runs on the CPU pool.

Randomness (RANSAC): each frame gets its own ``np.random.Generator``. Its seed is the
request's ``seed`` when given (the same frame, seed and map version give the same
answer), otherwise a fresh draw from the server's ``SeedSequence`` (seeded by
``MONOLOC_LOCALIZE_SEED``, OS entropy when unset). The answer reports the seed used.
"""

from __future__ import annotations

import time

import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.geo import GeoReference
from monoloc.server.api.convert import localize_response
from monoloc.server.api.deps import AppState
from monoloc.server.api.limits import ImageInfo, check_image, decode_gray
from monoloc.server.api.schemas_localize import LocalizeOptions, LocalizeResponse
from monoloc.server.localize import LocalizeConfig
from monoloc.server.settings import Settings
from monoloc.server.storage.cameras import CameraRecord, get_camera
from monoloc.server.storage.db import session_scope


def localize_config(settings: Settings) -> LocalizeConfig:
    """The pipeline a server runs on every query frame: the product's one pipeline (its
    deployment knobs are threads and limits, not algorithm variants)."""
    return LocalizeConfig()


def _intrinsics(
    state: AppState, map_id: int, info: ImageInfo, options: LocalizeOptions
) -> CameraIntrinsics | None:
    if options.focal is not None:
        fx, fy, cx, cy = options.focal
        return CameraIntrinsics(fx, fy, cx, cy, info.width_px, info.height_px, options.lens)
    if options.camera_id is not None:
        record = state.cameras.get(options.camera_id, lambda i: _load_camera(state, i))
        camera = record.intrinsics
        if (camera.width_px, camera.height_px) != (info.width_px, info.height_px):
            raise InvalidInputError(
                f"the image is {info.width_px}x{info.height_px} but camera {record.id} "
                f"({record.name!r}) takes {camera.width_px}x{camera.height_px} images: "
                "register this image size's camera"
            )
        return camera
    camera = state.registry.get(map_id).record.camera
    if (camera.width_px, camera.height_px) != (info.width_px, info.height_px):
        raise InvalidInputError(
            f"the image is {info.width_px}x{info.height_px} but the map's camera is "
            f"{camera.width_px}x{camera.height_px}: send fx, fy, cx, cy (or a registered "
            "camera_id) for this image"
        )
    return None


def _load_camera(state: AppState, camera_id: int) -> CameraRecord:
    with session_scope(state.sessions) as session:
        return get_camera(session, camera_id)


def localize_encoded(
    state: AppState, map_id: int, data: bytes, info: ImageInfo, options: LocalizeOptions
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
        localize_config(state.settings),
        np.random.default_rng(seed),
        intrinsics,
        options.prior,
        options.k,
    )
    timings = {"decode": decode_ms, **result.timings_ms}
    timings["total"] = result.timings_ms.get("total", 0.0) + decode_ms
    state.metrics.observe_localize(timings)
    stored = state.registry.get(map_id).record.geo_reference
    geo = GeoReference.from_dict(stored) if stored is not None else None
    answer = localize_response(map_id, version, result, timings, seed, geo)
    state.metrics.count_frame(map_id, "hypotheses" if answer.hypotheses else "no_hypothesis")
    return answer


async def localize_bytes(
    state: AppState, map_id: int, data: bytes, options: LocalizeOptions
) -> LocalizeResponse:
    """Check the image header on the loop (cheap), run the rest on the CPU pool."""
    info = check_image(data, "image", state.settings.max_image_pixels)
    return await state.run_cpu(localize_encoded, state, map_id, data, info, options)
