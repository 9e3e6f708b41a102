"""Blur + ORB feature extraction (docs/method.md section 2).

Query frames and mapping images go through exactly the same function, so a map entry and
a query are always described the same way.

ORB keeps the ``max_features`` corners with the highest Harris response over the whole
image (docs/method.md's rule, ``OrbConfig(grid_cells=None)``). monoloc's default spreads them
over the image instead, as ORB-SLAM's extractor does: ORB is asked for
``candidates_factor`` times as many corners, and the kept ones are taken cell by cell over
a ``grid_cells`` grid (each cell's strongest first, then each cell's second, ...), so a
facade in the shade keeps its corners beside one in the sun. Why (docs/notebook/features.md,
"ORB features spread over the image"): with the whole-image rule the corners follow the
light, and a query driven under a sun opposite to the map's (one side of the street bright
in one run, the other side in the other) shared too few of them with the map to find its
street.

On the grid, FAST's contrast threshold is also two-level, as ORB-SLAM's (20, and 7 where
a cell finds nothing): an image with fewer than ``flat_fast_corners`` FAST corners at
``fast_threshold`` at full resolution (a run under flat light, plain facades; counting
them costs 0.3 ms) is described by ORB at ``min_fast_threshold`` (12: as good as 7 on
the development cities, at two thirds of its cost). With one fixed threshold a whole query run of
such frames found no street (docs/notebook/features.md, "Two FAST thresholds on the grid").
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.server.vision.sizes import DESCRIPTOR_BYTES


@dataclass(frozen=True)
class OrbConfig:
    """Pre-filter and OpenCV ORB settings. Defaults are docs/method.md's (5x5 blur, 1000 features).

    ``blur_ksize`` is the side of the Gaussian kernel (odd; sigma derived by OpenCV from the
    size, 1.1 px for 5); 1 disables the blur. The ORB parameters map one to one onto
    ``cv2.ORB_create`` (OpenCV defaults), with ``patch_size`` = ``edge_threshold``.
    """

    max_features: int = 1000
    blur_ksize: int = 5
    scale_factor: float = 1.2
    n_levels: int = 8
    edge_threshold: int = 31
    fast_threshold: int = 20
    # Spread over the image (module doc): (columns, rows) of the grid the kept corners are
    # taken from in turns, and how many times ``max_features`` candidates ORB is asked for;
    # None: ORB's own strongest ``max_features`` (the paper's).
    grid_cells: tuple[int, int] | None = (8, 5)
    candidates_factor: float = 2.0
    # On the grid, a flat image is described at ``min_fast_threshold`` (None: always at
    # ``fast_threshold``): one with fewer than ``flat_fast_corners`` FAST corners at
    # ``fast_threshold`` at full resolution, or (``flat_fast_corners`` None: a grid map
    # recorded on 2026-11-28 before the count) one whose ORB gives fewer than
    # ``max_features`` corners at ``fast_threshold``, detected again.
    min_fast_threshold: int | None = 12
    flat_fast_corners: int | None = 150

    def __post_init__(self) -> None:
        if self.max_features < 1:
            raise InvalidInputError(f"OrbConfig.max_features must be >= 1, got {self.max_features}")
        if self.blur_ksize < 1 or self.blur_ksize % 2 == 0:
            raise InvalidInputError(
                f"OrbConfig.blur_ksize must be odd and >= 1, got {self.blur_ksize}"
            )
        if not self.scale_factor > 1.0 or self.n_levels < 1:
            raise InvalidInputError(
                f"OrbConfig needs scale_factor > 1 and n_levels >= 1, got "
                f"{self.scale_factor}, {self.n_levels}"
            )
        if self.edge_threshold < 1 or self.fast_threshold < 1:
            raise InvalidInputError(
                f"OrbConfig thresholds must be >= 1, got edge {self.edge_threshold}, "
                f"fast {self.fast_threshold}"
            )
        if self.grid_cells is not None and (len(self.grid_cells) != 2 or min(self.grid_cells) < 1):
            raise InvalidInputError(
                f"OrbConfig.grid_cells must be two counts >= 1 or None, got {self.grid_cells}"
            )
        if self.min_fast_threshold is not None and not (
            1 <= self.min_fast_threshold <= self.fast_threshold
        ):
            raise InvalidInputError(
                f"OrbConfig.min_fast_threshold must be in [1, fast_threshold], got "
                f"{self.min_fast_threshold}"
            )
        if self.flat_fast_corners is not None and self.flat_fast_corners < 1:
            raise InvalidInputError(
                f"OrbConfig.flat_fast_corners must be >= 1, got {self.flat_fast_corners}"
            )
        if not self.candidates_factor >= 1.0:
            raise InvalidInputError(
                f"OrbConfig.candidates_factor must be >= 1, got {self.candidates_factor}"
            )

    @property
    def n_candidates(self) -> int:
        """Corners asked of ORB: ``max_features``, times ``candidates_factor`` on a grid."""
        if self.grid_cells is None:
            return self.max_features
        return max(self.max_features, round(self.candidates_factor * self.max_features))


@dataclass(frozen=True, eq=False)
class Features:
    """ORB features of one image.

    keypoints_px: (N, 2) float32 pixel (x, y); pixel (0, 0) is the centre of the top-left
    pixel (OpenCV's convention). descriptors: (N, 32) uint8, row i describes keypoint i.
    scales: (N,) float32, the pyramid scale each keypoint was found at
    (``scale_factor ** octave``, 1 = full resolution): its position is that much coarser;
    None unless asked for (``extract_features(..., scales=True)``: reading them off
    OpenCV's keypoints costs about 0.1 ms a frame, which only PnP's opt-in scale weighting
    uses).
    """

    keypoints_px: np.ndarray
    descriptors: np.ndarray
    scales: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.keypoints_px.shape[0])


def empty_features() -> Features:
    """N = 0 features with the right shapes and dtypes."""
    return Features(
        keypoints_px=np.zeros((0, 2), dtype=np.float32),
        descriptors=np.zeros((0, DESCRIPTOR_BYTES), dtype=np.uint8),
        scales=np.zeros(0, dtype=np.float32),
    )


def as_gray_uint8(image: np.ndarray) -> np.ndarray:
    """Validate an image and return it as (H, W) uint8.

    Accepts (H, W), (H, W, 1) or (H, W, 3) uint8; three channels are taken as RGB (the
    order scikit-image and PIL use; convert BGR from ``cv2.imread`` first, or pass gray).
    """
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise InvalidInputError(f"image must be uint8, got dtype {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    elif image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    elif image.ndim != 2:
        raise InvalidInputError(f"image must be (H, W) or (H, W, 3) uint8, got shape {image.shape}")
    return np.ascontiguousarray(image)


def _create_orb(config: OrbConfig, n_features: int | None = None) -> cv2.ORB:
    # A fresh detector per call is negligible next to detectAndCompute, and a shared
    # cv2.ORB is not documented as thread-safe, so there is no cache to get wrong.
    return cv2.ORB_create(
        nfeatures=n_features or config.max_features,
        scaleFactor=config.scale_factor,
        nlevels=config.n_levels,
        edgeThreshold=config.edge_threshold,
        firstLevel=0,
        WTA_K=2,
        scoreType=cv2.ORB_HARRIS_SCORE,
        patchSize=config.edge_threshold,
        fastThreshold=config.fast_threshold,
    )


def extract_features(
    image_gray: np.ndarray, config: OrbConfig = OrbConfig(), scales: bool = False
) -> Features:
    """Gaussian blur (``config.blur_ksize`` square) then ORB; at most ``max_features``.

    image_gray: (H, W) uint8 (or (H, W, 3) uint8 RGB, converted to gray). Returns
    :class:`Features`; an image without corners (flat, tiny, empty) gives N = 0.
    Raises InvalidInputError on a wrong dtype or shape.
    """
    gray = as_gray_uint8(image_gray)
    if min(gray.shape) < 2 * config.edge_threshold + 1:
        # No keypoint fits inside ORB's border (and OpenCV asserts on 1-pixel sides).
        return empty_features()
    if config.blur_ksize > 1:
        gray = cv2.GaussianBlur(gray, (config.blur_ksize, config.blur_ksize), 0)
    keypoints, descriptors = _detect_and_compute(gray, config)
    if descriptors is None or len(keypoints) == 0:
        return empty_features()
    points_px = cv2.KeyPoint_convert(keypoints).astype(np.float32, copy=False).reshape(-1, 2)
    descriptors = descriptors.reshape(-1, DESCRIPTOR_BYTES)
    keep = None
    if config.grid_cells is not None and len(keypoints) > config.max_features:
        response = np.fromiter((k.response for k in keypoints), np.float64, len(keypoints))
        keep = spread_over_grid(
            points_px, response, gray.shape, config.grid_cells, config.max_features
        )
        points_px, descriptors = points_px[keep], descriptors[keep]
    octaves = None
    if scales:
        octaves = np.fromiter((k.octave for k in keypoints), np.float32, len(keypoints))
        octaves = octaves if keep is None else octaves[keep]
    return Features(
        keypoints_px=np.ascontiguousarray(points_px),
        descriptors=np.ascontiguousarray(descriptors, dtype=np.uint8),
        scales=None if octaves is None else np.float32(config.scale_factor) ** octaves,
    )


def _detect_and_compute(gray: np.ndarray, config: OrbConfig):
    """ORB's keypoints and descriptors of the blurred image at ``fast_threshold``, or at
    ``min_fast_threshold`` when the image is flat (see ``OrbConfig``)."""
    two_level = (
        config.grid_cells is not None
        and config.min_fast_threshold is not None
        and config.min_fast_threshold < config.fast_threshold
    )
    low = replace(config, fast_threshold=config.min_fast_threshold) if two_level else config
    if two_level and config.flat_fast_corners is not None:
        fast = cv2.FastFeatureDetector_create(threshold=config.fast_threshold)
        flat = len(fast.detect(gray, None)) < config.flat_fast_corners
        return _create_orb(low if flat else config, config.n_candidates).detectAndCompute(
            gray, None
        )
    keypoints, descriptors = _create_orb(config, config.n_candidates).detectAndCompute(gray, None)
    if two_level and len(keypoints) < config.max_features:
        keypoints, descriptors = _create_orb(low, config.n_candidates).detectAndCompute(gray, None)
    return keypoints, descriptors


def selection_rule(config: OrbConfig = OrbConfig()) -> dict:
    """How ``config`` picks the corners it keeps, as a map records it for its entries:
    ``{"rule": "strongest"}`` (ORB's own, the whole image) or ``{"rule": "grid",
    "grid_cells": [columns, rows], "candidates_factor": f, "fast_thresholds": [t, t_min],
    "flat_fast_corners": n}`` (a grid map recorded before the second threshold has no
    ``fast_thresholds``: one pass at 20). Entries and queries picked by different rules
    share fewer corners (docs/notebook/features.md, "ORB features spread over the image")."""
    if config.grid_cells is None:
        return {"rule": "strongest"}
    rule = {
        "rule": "grid",
        "grid_cells": [int(c) for c in config.grid_cells],
        "candidates_factor": float(config.candidates_factor),
    }
    if config.min_fast_threshold is not None:
        rule["fast_thresholds"] = [int(config.fast_threshold), int(config.min_fast_threshold)]
        if config.flat_fast_corners is not None:
            rule["flat_fast_corners"] = int(config.flat_fast_corners)
    return rule


def orb_for_rule(recorded: dict | None, config: OrbConfig = OrbConfig()) -> OrbConfig:
    """``config`` picking its corners the way a map recorded for its entries
    (:func:`selection_rule`), so that the entries added to a map later and the queries
    against it are described as its first entries were; None (nothing recorded):
    ``config`` as it is. InvalidInputError on a rule this code does not know."""
    if not recorded:
        return config
    rule = recorded.get("rule")
    if rule == "strongest":
        return replace(config, grid_cells=None)
    if rule == "grid":
        try:
            columns, rows = (int(c) for c in recorded["grid_cells"])
            factor = float(recorded["candidates_factor"])
            # before the second threshold: one pass at ORB's 20
            fast, low = (int(t) for t in recorded.get("fast_thresholds", (20, 0)))
            flat = recorded.get("flat_fast_corners")
            if flat is None and not low:
                flat = config.flat_fast_corners  # unused with one threshold
            return replace(
                config,
                grid_cells=(columns, rows),
                candidates_factor=factor,
                fast_threshold=fast,
                min_fast_threshold=low or None,
                flat_fast_corners=None if flat is None else int(flat),
            )
        except (KeyError, TypeError, ValueError, InvalidInputError) as exc:
            raise InvalidInputError(f"a map's ORB rule is malformed: {recorded!r}") from exc
    raise InvalidInputError(f"unknown ORB corner rule {rule!r} (strongest or grid)")


def rule_is_current(recorded: dict | None, config: OrbConfig = OrbConfig()) -> bool:
    """Whether a map recorded the rule ``config`` (the server's default) picks corners by
    (:func:`selection_rule`; None, nothing recorded, counts as current). A map of another
    rule is served by its own rule (:func:`orb_for_rule`): it works as it did, without the
    default's gain."""
    return recorded is None or dict(recorded) == selection_rule(config)


def rule_text(recorded: dict | None) -> str:
    """A map's recorded rule for people: "grid 8x5, FAST 20/12", "strongest" or "-"."""
    if not recorded:
        return "-"
    if recorded.get("rule") == "grid":
        columns, rows = recorded.get("grid_cells", ("?", "?"))
        thresholds = recorded.get("fast_thresholds")
        fast = "/".join(str(t) for t in thresholds) if thresholds else "20"
        return f"grid {columns}x{rows}, FAST {fast}"
    return str(recorded.get("rule", "?"))


def spread_over_grid(
    points_px: np.ndarray,
    response: np.ndarray,
    image_shape: tuple[int, int],
    grid_cells: tuple[int, int],
    n: int,
) -> np.ndarray:
    """Indices of at most n of the keypoints (N, 2) pixel (x, y), taken in turns over a
    ``grid_cells`` (columns, rows) grid of an image of ``image_shape`` (H, W): every
    cell's strongest (``response`` (N,)) first, then every cell's second, and so on, the
    stronger first within a turn; sorted, so the kept keypoints keep ORB's order."""
    height, width = image_shape
    columns, rows = grid_cells
    col = np.clip((points_px[:, 0] * (columns / width)).astype(np.int64), 0, columns - 1)
    row = np.clip((points_px[:, 1] * (rows / height)).astype(np.int64), 0, rows - 1)
    cell = row * columns + col
    by_cell = np.lexsort((-response, cell))  # cell by cell, strongest first
    cell_sorted = cell[by_cell]
    turn = np.empty(len(cell), dtype=np.int64)
    turn[by_cell] = np.arange(len(cell)) - np.searchsorted(cell_sorted, cell_sorted)
    return np.sort(np.lexsort((-response, turn))[:n])


def _intensity_centroid_angles_deg(gray: np.ndarray, centres: np.ndarray, radius: int):
    """ORB's orientation (intensity centroid over a disc of ``radius``) at integer pixel
    centres (N, 2) int (x, y), in degrees [0, 360), as OpenCV's ORB computes it at level 0."""
    dy, dx = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    disc = (dx * dx + dy * dy) <= radius * radius + radius  # OpenCV's rounded circle
    image = gray.astype(np.float64)
    angles = np.empty(len(centres), dtype=np.float64)
    for i, (x, y) in enumerate(centres):
        patch = image[y - radius : y + radius + 1, x - radius : x + radius + 1] * disc
        angles[i] = np.degrees(np.arctan2((dy * patch).sum(), (dx * patch).sum()))
    return np.mod(angles, 360.0)


def describe_keypoints(
    image_gray: np.ndarray, keypoints_px: np.ndarray, config: OrbConfig = OrbConfig()
) -> tuple[np.ndarray, np.ndarray]:
    """ORB descriptors at given pixel positions (e.g. a COLMAP model's observations), as
    :func:`extract_features` would describe a keypoint detected there at full resolution:
    same blur, ORB's own orientation (intensity centroid) and patch.

    keypoints_px: (N, 2) float pixel (x, y), OpenCV convention. Returns (kept (N,) bool,
    descriptors (K, 32) uint8) for the K kept keypoints: those whose patch lies inside the
    image (closer than ``edge_threshold`` to a border: dropped, as ORB drops them).
    """
    gray = as_gray_uint8(image_gray)
    points = np.asarray(keypoints_px, dtype=np.float64).reshape(-1, 2)
    height, width = gray.shape
    border = config.edge_threshold
    centres = np.rint(points).astype(np.int64)
    kept = (
        np.all(np.isfinite(points), axis=1)
        & (centres[:, 0] >= border)
        & (centres[:, 0] < width - border)
        & (centres[:, 1] >= border)
        & (centres[:, 1] < height - border)
    )
    if not kept.any():
        return kept, np.zeros((0, DESCRIPTOR_BYTES), dtype=np.uint8)
    if config.blur_ksize > 1:
        gray = cv2.GaussianBlur(gray, (config.blur_ksize, config.blur_ksize), 0)
    angles = _intensity_centroid_angles_deg(gray, centres[kept], config.edge_threshold // 2)
    keypoints = [
        cv2.KeyPoint(float(x), float(y), float(config.edge_threshold), float(a), 0.0, 0)
        for (x, y), a in zip(points[kept], angles, strict=True)
    ]
    described, descriptors = _create_orb(config).compute(gray, keypoints)
    if descriptors is None or len(described) != len(keypoints):
        raise InvalidInputError("ORB dropped keypoints inside the border")  # never expected
    return kept, np.ascontiguousarray(descriptors, dtype=np.uint8)
