"""Relative pose of a query camera from 2D-3D matches with one reference (docs/method.md 6.3-6.4).

PnP solves for T_query_from_ref (camera = query, object points in the reference camera
frame); the result is inverted to T_ref_from_query. A reference that gives no credible
pose is *rejected* (``accepted=False`` with a reason), never raised: a bad reference is
an ordinary outcome of retrieval.

Randomness: the injected ``rng`` drives RANSAC. :func:`estimate_relative_pose` seeds
OpenCV's (per-thread) global RNG with ``cv2.setRNGSeed(rng.integers(2**31))`` right before
``cv2.solvePnPRansac``, so single-threaded runs with the same ``rng`` state are
reproducible. Measured with OpenCV 5.0: its PnP RANSAC seeds its sampler with a constant
and ignores the global RNG, so the call alone would be deterministic but deaf to ``rng``;
the correspondences are therefore also shuffled with ``rng`` before the call, which makes
the samples depend on ``rng`` (and only on it) whatever the OpenCV version does. With
``PnpConfig.ransac == "usac"`` the same draw seeds USAC's own generator
(``UsacParams.randomGeneratorState``), after the same shuffle.

Pipeline: RANSAC with P3P hypotheses on 4-point samples (several times faster than
OpenCV's default EPnP 5-point kernel at equal accuracy; bench/vision.py), then SQPnP on
the RANSAC inliers, re-selection of the inliers with that pose, and, with ``refine``,
Levenberg-Marquardt on them and a last re-selection (see :func:`_refit` for why). The
inlier scoring and LM are compiled (``monoloc.server.vision._pnp_kernel``; its LM reaches
OpenCV's solvePnPRefineLM optimum, faster: bench/vision.py times both).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.core.geometry import invert_rigid, rotation_angle_rad

# Below this many points no solver gives a checked pose (P3P samples 4, EPnP 5).
_MIN_POINTS_FOR_SOLVER = 6


# "opencv": cv2.solvePnPRansac's classic RANSAC with P3P samples and the budget of
# :func:`ransac_iterations`; "usac": OpenCV's USAC framework (uniform sampling, MSAC
# score, its own adaptive stop within ``iterations``; the minimal solver is its own).
RANSAC_METHODS = ("opencv", "usac")


@dataclass(frozen=True)
class PnpConfig:
    """PnP RANSAC settings.

    reprojection_error_px: RANSAC inlier threshold (3 px: on the bench scene, ORB
    keypoints of a warped real photograph lie a median 0.75 px from their exact
    projection and 97 % within 3 px); iterations / confidence: RANSAC
    budget (stops early once ``confidence`` is reached); min_inliers: fewer inliers means
    reject (docs/method.md 6.4, monoloc's minimum); max_rotation_rad: reject relative
    rotations above this, None = the camera's horizontal field of view (docs/method.md 6.4);
    refine: Levenberg-Marquardt on the inliers after RANSAC, at most
    ``refine_iterations`` accepted steps (started from the SQPnP refit, two steps matched
    twenty to 0.5 mm on the bench scene). RANSAC's hypotheses come from P3P (the fastest
    at equal accuracy in bench/vision.py).

    Every correspondence counts alike: weighing each error by its keypoint's pyramid scale
    tightened the per-entry poses but not the filter (docs/notebook), so scales weigh only
    the joint pose's robust refit (:func:`robust_refit`) and the pose covariances.

    Guided PnP (:func:`estimate_relative_pose_guided`): a pose guessed from elsewhere
    chooses the entry's consensus set (its correspondences within the threshold), which is
    refit as RANSAC's would be; the result is kept when it holds at least
    max(min_inliers, guided_min_inlier_ratio x matches) inliers; otherwise the entry gets
    its own full RANSAC. The refit is tried only when the guess keeps at least
    ``guided_refit_min_fraction`` of those inliers: on bench/localize.py's queries a refit
    never lifted a guess below 0.8 of them to enough (1 in 56 from 0.8-0.9, 4 in 17 from
    0.9-1), and the 227 of 318 rejected entries below 0.5 each paid an SQPnP + LM for
    nothing.
    """

    reprojection_error_px: float = 3.0
    iterations: int = 200
    confidence: float = 0.999
    min_inliers: int = 15
    max_rotation_rad: float | None = None
    refine: bool = True
    refine_iterations: int = 2
    guided_min_inlier_ratio: float = 0.3
    guided_refit_min_fraction: float = 0.5
    ransac: str = "opencv"

    def __post_init__(self) -> None:
        if not self.reprojection_error_px > 0 or self.iterations < 1:
            raise InvalidInputError(f"invalid PnpConfig {self}")
        if not 0.0 < self.confidence < 1.0 or self.min_inliers < 1 or self.refine_iterations < 1:
            raise InvalidInputError(f"invalid PnpConfig {self}")
        if self.max_rotation_rad is not None and not self.max_rotation_rad > 0:
            raise InvalidInputError(f"PnpConfig.max_rotation_rad must be > 0: {self}")
        if not (0.0 <= self.guided_min_inlier_ratio <= 1.0) or not (
            0.0 <= self.guided_refit_min_fraction <= 1.0
        ):
            raise InvalidInputError(f"invalid PnpConfig guided settings {self}")
        if self.ransac not in RANSAC_METHODS:
            raise InvalidInputError(
                f"PnpConfig.ransac must be one of {RANSAC_METHODS}, got {self.ransac!r}"
            )


@dataclass(frozen=True, eq=False)
class RelativePose:
    """Outcome of PnP against one reference.

    T_ref_from_query: (4, 4) float64, maps query-camera points to reference-camera
    points; all NaN when no pose was estimated. n_inliers / inlier_mask (M,) bool: the
    correspondences within ``reprojection_error_px`` of the final pose (and in front of
    the query camera). reprojection_error_px: mean over the inliers (NaN without any).
    accepted: False when rejected, with ``reject_reason`` saying why. method: how the
    pose was found, "ransac" (the entry's own RANSAC) or "guided" (a pose found elsewhere,
    re-scored and refined on this entry's own correspondences).
    """

    T_ref_from_query: np.ndarray
    n_inliers: int
    inlier_mask: np.ndarray
    reprojection_error_px: float
    accepted: bool
    reject_reason: str | None = None
    method: str = "ransac"


def _rejected(
    n_points: int,
    reason: str,
    T_ref_from_query: np.ndarray | None = None,
    inlier_mask: np.ndarray | None = None,
    error_px: float = float("nan"),
    method: str = "ransac",
) -> RelativePose:
    mask = np.zeros(n_points, dtype=bool) if inlier_mask is None else inlier_mask
    return RelativePose(
        T_ref_from_query=np.full((4, 4), np.nan) if T_ref_from_query is None else T_ref_from_query,
        n_inliers=int(np.count_nonzero(mask)),
        inlier_mask=mask,
        reprojection_error_px=error_px,
        accepted=False,
        reject_reason=reason,
        method=method,
    )


# LM weights meaning "all 1" (the kernel's convention): no array to allocate per call.
_UNIT_WEIGHTS = np.empty(0)
# refine_rounds' "every correspondence may be an inlier"
_NO_CANDIDATES = np.empty(0, dtype=bool)


def _weighted_lm(
    points: np.ndarray,
    pixels: np.ndarray,
    mask: np.ndarray,
    weights: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    config: PnpConfig,
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """LM on the masked correspondences, each squared error weighted by ``weights`` (M,),
    and the reprojection errors (M,) px at its pose; all None if LM left the finite
    numbers."""
    from monoloc.server.vision._pnp_kernel import refine_lm

    R, t, _ = refine_lm(
        points, pixels, mask, weights, R, t, K[0, 0], K[1, 1], K[0, 2], K[1, 2],
        config.refine_iterations,
    )  # fmt: skip
    if not _finite(R, t):
        return None, None, None
    _, errors_px = _inliers(points, pixels, R, t, K, config.reprojection_error_px)
    return R, t, errors_px


def _inliers(
    points: np.ndarray,
    pixels: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    threshold_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Inlier mask (within ``threshold_px`` and in front of the camera) and reprojection
    errors (M,) px of the pose (R_query_from_ref, t_query_from_ref)."""
    from monoloc.server.vision._pnp_kernel import inlier_errors

    errors_px = np.empty(len(points))
    mask = np.empty(len(points), dtype=bool)
    inlier_errors(
        points, pixels, R, t, K[0, 0], K[1, 1], K[0, 2], K[1, 2], threshold_px, errors_px, mask
    )
    return mask, errors_px


def within_threshold(
    pixels_px: np.ndarray,
    points_ref: np.ndarray,
    T_query_from_ref: np.ndarray,
    intrinsics: CameraIntrinsics,
    threshold_px: float,
) -> np.ndarray:
    """(M,) bool: which correspondences (query pixels (M, 2), 3D points (M, 3) in the
    reference camera frame) the pose ``T_query_from_ref`` (4, 4) puts in front of the
    camera and within ``threshold_px`` of their pixel (PnP's inlier test)."""
    T = np.asarray(T_query_from_ref, dtype=np.float64)
    mask, _ = _inliers(
        np.ascontiguousarray(points_ref, dtype=np.float64),
        np.ascontiguousarray(pixels_px, dtype=np.float64),
        np.ascontiguousarray(T[:3, :3]),
        np.ascontiguousarray(T[:3, 3]),
        intrinsics.K,
        threshold_px,
    )
    return mask


def _refit(
    points: np.ndarray,
    pixels: np.ndarray,
    mask: np.ndarray,
    K: np.ndarray,
    config: PnpConfig,
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray, np.ndarray]:
    """Pose from RANSAC's inliers: SQPnP refit, inlier re-selection, then optional LM.

    Why not the pose solvePnPRansac returns: with P3P samples OpenCV refits the inliers
    with EPnP, which was measured to fail outright on near-planar scenes (50 deg off on a
    textured wall), and early termination leaves an inlier set chosen by a 4-point model.
    SQPnP (globally optimal, planar-safe, cheap next to RANSAC) on those inliers, then
    re-selecting the inliers with that better pose, fixes both; LM then minimises the
    reprojection error (``_pnp_kernel.refine_lm``) and re-selects the inliers. Returns
    (R_query_from_ref (3, 3), t_query_from_ref (3,), final inlier mask, errors_px (M,)); R
    is None if a solver gave nothing finite.
    """
    from monoloc.server.vision._pnp_kernel import refine_rounds

    ok, rvec, tvec = cv2.solvePnP(points[mask], pixels[mask], K, None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok or not math.isfinite(float(rvec.sum()) + float(tvec.sum())):
        return None, None, mask, np.full(len(mask), np.inf)
    R, t = cv2.Rodrigues(rvec)[0], tvec.reshape(3).astype(np.float64)
    if not config.refine:
        mask, errors_px = _inliers(points, pixels, R, t, K, config.reprojection_error_px)
        return R, t, mask, errors_px
    # one round of refine_rounds is this refit's tail in one call: the selection, LM on
    # it when it holds 6 or more (status 1: fewer, the SQPnP pose stays), the last
    # selection (status 2: LM left the finite numbers)
    errors_px = np.empty(len(points))
    mask = np.empty(len(points), dtype=bool)
    R, t, status = refine_rounds(
        points, pixels, _NO_CANDIDATES, R, t, K[0, 0], K[1, 1], K[0, 2], K[1, 2],
        config.reprojection_error_px, 1, config.refine_iterations, errors_px, mask,
    )  # fmt: skip
    if status == 2:
        return None, None, mask, errors_px
    return R, t, mask, errors_px


def _ref_from_query(R_query_from_ref: np.ndarray, t_query_from_ref: np.ndarray) -> np.ndarray:
    """(4, 4) T_ref_from_query of the pose (R_query_from_ref (3, 3), t (3,)): the inverse
    ``invert_rigid`` would give of the assembled T_query_from_ref, without assembling it."""
    R_t = R_query_from_ref.T
    T = np.empty((4, 4))
    T[:3, :3] = R_t
    T[:3, 3] = -R_t @ t_query_from_ref
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return T


def ransac_iterations(n_points: int, config: PnpConfig) -> int:
    """RANSAC iterations worth running on ``n_points`` matches.

    A reference is accepted only with >= ``min_inliers`` inliers, so its inlier ratio is at
    least w = min_inliers / n_points. Drawing a 3-point all-inlier sample with probability
    ``confidence`` then takes log(1 - confidence) / log(1 - w^3) iterations; more cannot
    change the verdict. With few matches (the usual wrong reference) that is a handful
    instead of ``config.iterations``, which made rejections the bulk of PnP time.
    """
    w = min(1.0, config.min_inliers / max(n_points, 1))
    if w >= 1.0:
        return 1
    needed = math.log(1.0 - config.confidence) / math.log(1.0 - w**3)
    return int(max(1, min(config.iterations, math.ceil(needed))))


def estimate_relative_pose(
    points_query_px: np.ndarray,
    points_ref_cam: np.ndarray,
    intrinsics: CameraIntrinsics,
    config: PnpConfig,
    rng: np.random.Generator,
) -> RelativePose:
    """PnP RANSAC on M matches: query pixels (M, 2) and their 3D points in the reference
    camera frame (M, 3), metres. Returns T_ref_from_query and inlier statistics.

    Rejects (accepted=False) on: too few correspondences, RANSAC failure, fewer than
    ``min_inliers`` inliers, relative rotation above ``max_rotation_rad`` (default: the
    horizontal FOV). Raises InvalidInputError only for malformed arrays.
    """
    pixels, points = _checked_correspondences(points_query_px, points_ref_cam)
    n_points = len(pixels)
    if n_points < max(config.min_inliers, _MIN_POINTS_FOR_SOLVER):
        return _rejected(n_points, f"too few correspondences ({n_points})")
    K = intrinsics.K
    try:
        mask = _ransac_inliers(points, pixels, K, config, rng)
        if mask is None:
            return _rejected(n_points, "PnP RANSAC found no pose")
        R_query_from_ref, t_query_from_ref, mask, errors_px = _refit(
            points, pixels, mask, K, config
        )
    except cv2.error as exc:  # degenerate input (e.g. all points identical)
        return _rejected(n_points, f"PnP failed: {str(exc).strip().splitlines()[-1]}")
    if R_query_from_ref is None:
        return _rejected(n_points, "PnP refit on the RANSAC inliers failed")
    T_ref_from_query = _ref_from_query(R_query_from_ref, t_query_from_ref)
    return _judged(T_ref_from_query, mask, errors_px, intrinsics, config)


def _checked_correspondences(
    points_query_px: np.ndarray, points_ref_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """float64 (M, 2) pixels and (M, 3) points; InvalidInputError if malformed."""
    pixels = np.asarray(points_query_px, dtype=np.float64)
    points = np.asarray(points_ref_cam, dtype=np.float64)
    if pixels.ndim != 2 or pixels.shape[1] != 2 or points.ndim != 2 or points.shape[1] != 3:
        raise InvalidInputError(
            f"need (M, 2) query pixels and (M, 3) reference points, got {pixels.shape}, "
            f"{points.shape}"
        )
    if len(pixels) != len(points):
        raise InvalidInputError(f"{len(pixels)} query pixels but {len(points)} reference points")
    # A finite sum is the cheap proof (it runs per entry and query); only a NaN, an
    # infinity or an overflow to one takes the element-wise test.
    if not math.isfinite(float(pixels.sum()) + float(points.sum())) and not (
        np.isfinite(pixels).all() and np.isfinite(points).all()
    ):
        raise InvalidInputError("query pixels or reference points contain NaN or infinite values")
    return pixels, points


def _finite(*arrays: np.ndarray) -> bool:
    """Whether a few small arrays (a pose) hold only finite numbers (NaN and infinities
    propagate through the sum; a pose whose sum overflows is no pose either)."""
    return math.isfinite(sum(sum(a.ravel().tolist()) for a in arrays))


def _ransac_inliers(
    points: np.ndarray,
    pixels: np.ndarray,
    K: np.ndarray,
    config: PnpConfig,
    rng: np.random.Generator,
) -> np.ndarray | None:
    """RANSAC's inlier mask (M,) bool, or None when it found no pose. The samples depend
    on ``rng`` only (see the module docstring)."""
    n_points = len(pixels)
    order = rng.permutation(n_points)
    seed = int(rng.integers(2**31))
    if config.ransac == "usac":
        params = cv2.UsacParams()
        params.confidence = config.confidence
        params.maxIterations = config.iterations
        params.threshold = config.reprojection_error_px
        params.sampler = cv2.SAMPLING_UNIFORM
        params.score = cv2.SCORE_METHOD_MSAC
        params.loMethod = cv2.LOCAL_OPTIM_NULL
        params.randomGeneratorState = seed
        ok, _, _, _, inliers = cv2.solvePnPRansac(
            points[order], pixels[order], K, None, None, None, None, params
        )
    else:
        cv2.setRNGSeed(seed)
        ok, _, _, inliers = cv2.solvePnPRansac(
            points[order],
            pixels[order],
            K,
            None,
            iterationsCount=ransac_iterations(n_points, config),
            reprojectionError=config.reprojection_error_px,
            confidence=config.confidence,
            flags=cv2.SOLVEPNP_P3P,
        )
    if not ok or inliers is None or len(inliers) < _MIN_POINTS_FOR_SOLVER:
        return None
    mask = np.zeros(n_points, dtype=bool)
    mask[order[inliers.ravel()]] = True
    return mask


def _judged(
    T_ref_from_query: np.ndarray,
    mask: np.ndarray,
    errors_px: np.ndarray,
    intrinsics: CameraIntrinsics,
    config: PnpConfig,
    method: str = "ransac",
) -> RelativePose:
    """Accept the pose, or reject it for too few inliers or too large a rotation."""
    n_points = len(mask)
    n_inliers = int(np.count_nonzero(mask))
    # sum / n is np.mean's own arithmetic, without its Python-level wrapper
    mean_error = float(errors_px[mask].sum()) / n_inliers if n_inliers else float("nan")
    if n_inliers < config.min_inliers:
        return _rejected(
            n_points,
            f"{n_inliers} inliers < min_inliers {config.min_inliers}",
            T_ref_from_query,
            mask,
            mean_error,
        )
    max_rotation = (
        intrinsics.horizontal_fov_rad
        if config.max_rotation_rad is None
        else config.max_rotation_rad
    )
    angle = rotation_angle_rad(T_ref_from_query[:3, :3])
    if angle > max_rotation:
        return _rejected(
            n_points,
            f"relative rotation {np.degrees(angle):.1f} deg exceeds "
            f"{np.degrees(max_rotation):.1f} deg",
            T_ref_from_query,
            mask,
            mean_error,
        )
    return RelativePose(
        T_ref_from_query=T_ref_from_query,
        n_inliers=n_inliers,
        inlier_mask=mask,
        reprojection_error_px=mean_error,
        accepted=True,
        reject_reason=None,
        method=method,
    )


def refine_from_pose(
    points: np.ndarray,
    pixels: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    config: PnpConfig,
    rounds: int,
    candidates: np.ndarray | None = None,
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray, np.ndarray]:
    """Score the correspondences against a pose and refine it on its inliers, ``rounds``
    times: select the inliers of (R, t), Levenberg-Marquardt on them, then a last
    selection. The shared step of guided PnP and the joint pose.

    points (M, 3) float64 in the frame (R, t) maps to the query camera, pixels (M, 2)
    float64; ``candidates`` (M,) bool limits which correspondences may be inliers.
    Returns (R, t, inlier mask, errors_px (M,)); R is None if LM left the finite numbers
    or fewer than 6 inliers remained to refine on.
    """
    from monoloc.server.vision._pnp_kernel import refine_rounds

    errors_px = np.empty(len(points))
    mask = np.empty(len(points), dtype=bool)
    R, t, status = refine_rounds(
        points, pixels, _NO_CANDIDATES if candidates is None else candidates,
        np.ascontiguousarray(R, dtype=np.float64), np.ascontiguousarray(t, dtype=np.float64),
        K[0, 0], K[1, 1], K[0, 2], K[1, 2], config.reprojection_error_px, rounds,
        config.refine_iterations, errors_px, mask,
    )  # fmt: skip
    if status:
        return None, None, mask, errors_px
    return R, t, mask, errors_px


# the median of a 2D Gaussian error's length, in its per-axis sigmas (sqrt(2 ln 2))
_RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))
# noise-free correspondences: a floor for the robust sigma (px) so the loss stays finite
_MIN_SIGMA_PX = 1e-3


def robust_refit(
    points: np.ndarray,
    pixels: np.ndarray,
    mask: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    config: PnpConfig,
    keypoint_scales: np.ndarray,
    cauchy_scale_sigmas: float,
    rounds: int,
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray]:
    """(R, t) refined on the masked correspondences under a Cauchy loss: ``rounds`` of
    iteratively reweighted LM, each squared error weighted by 1 / (s^2 (1 + (e / (s c))^2))
    with e its reprojection error (px) at the current pose and s its keypoint's pyramid
    scale (``keypoint_scales`` (M,)). c is ``cauchy_scale_sigmas`` robust standard
    deviations of the inliers' errors at the starting pose (per axis, from the median of
    e / s: 1.1774 sigma for Gaussian errors), so the loss follows the data's own noise:
    2.385 keeps 95 % of least squares' efficiency on Gaussian errors. Why: the inliers
    within the RANSAC threshold carry a tail of matches off by one to three pixels (a
    corner found a little elsewhere in the query than in the map image); least squares
    lets that tail pull the pose, the Cauchy weights fade it out. The inliers stay those
    of ``mask``. Returns (R, t, errors_px (M,) at the final pose); R None if LM left the
    finite numbers."""
    scales = np.asarray(keypoint_scales, dtype=np.float64).reshape(-1)
    if len(scales) != len(points) or not (np.all(np.isfinite(scales)) and np.all(scales > 0)):
        raise InvalidInputError(
            f"need {len(points)} positive finite keypoint scales, got shape {scales.shape}"
        )
    if not (cauchy_scale_sigmas > 0 and rounds >= 1):
        raise InvalidInputError(
            f"robust_refit needs cauchy_scale_sigmas > 0 and rounds >= 1, got "
            f"{cauchy_scale_sigmas}, {rounds}"
        )
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        raise InvalidInputError("robust_refit needs at least one inlier")
    R = np.ascontiguousarray(R, dtype=np.float64)
    t = np.ascontiguousarray(t, dtype=np.float64)
    _, errors_px = _inliers(points, pixels, R, t, K, config.reprojection_error_px)
    sigma = float(np.median(errors_px[mask] / scales[mask])) / _RAYLEIGH_MEDIAN
    c = cauchy_scale_sigmas * max(sigma, _MIN_SIGMA_PX)
    for _ in range(rounds):
        u = errors_px / (scales * c)
        weights = 1.0 / (scales * scales * (1.0 + u * u))
        R_new, t_new, errors_new = _weighted_lm(points, pixels, mask, weights, R, t, K, config)
        if R_new is None:
            return None, None, errors_px
        R, t, errors_px = R_new, t_new, errors_new
    return R, t, errors_px


def refit_relative_pose(
    points_query_px: np.ndarray,
    points_ref_cam: np.ndarray,
    T_ref_from_query: np.ndarray,
    intrinsics: CameraIntrinsics,
    config: PnpConfig,
    method: str,
    rounds: int = 2,
) -> RelativePose:
    """A pose (4, 4) T_ref_from_query re-scored and refined on other correspondences
    (pixels (M, 2), points (M, 3) in the reference frame): inlier selection and LM
    ``rounds`` times (:func:`refine_from_pose`), then the usual checks; ``method`` is
    kept. Rejected when LM fails or fewer than ``min_inliers`` remain."""
    pixels, points = _checked_correspondences(points_query_px, points_ref_cam)
    T_query_from_ref = invert_rigid(np.asarray(T_ref_from_query, dtype=np.float64))
    return refit_checked(pixels, points, T_query_from_ref, intrinsics, config, method, rounds)


def refit_checked(
    pixels: np.ndarray,
    points: np.ndarray,
    T_query_from_ref: np.ndarray,
    intrinsics: CameraIntrinsics,
    config: PnpConfig,
    method: str,
    rounds: int = 2,
) -> RelativePose:
    """:func:`refit_relative_pose` on correspondences already checked (float64 pixels
    (M, 2) and points (M, 3), finite) from the pose (4, 4) T_query_from_ref: the refit of
    every accepted entry on its matches by projection, which pays no checks or inversion
    twice."""
    n_points = len(pixels)
    if n_points < _MIN_POINTS_FOR_SOLVER:
        return _rejected(n_points, f"{n_points} correspondences to refit on", method=method)
    R, t, mask, errors_px = refine_from_pose(
        points, pixels, T_query_from_ref[:3, :3], T_query_from_ref[:3, 3], intrinsics.K,
        config, rounds,
    )  # fmt: skip
    if R is None:
        return _rejected(
            n_points, "the refit left too few inliers or finite numbers", method=method
        )
    return _judged(_ref_from_query(R, t), mask, errors_px, intrinsics, config, method)


def guided_min_inliers(n_points: int, config: PnpConfig) -> int:
    """The fewest inliers a guided pose must keep to stand without the entry's own RANSAC."""
    return max(config.min_inliers, math.ceil(config.guided_min_inlier_ratio * n_points))


def estimate_relative_pose_guided(
    points_query_px: np.ndarray,
    points_ref_cam: np.ndarray,
    guesses_T_ref_from_query: list[np.ndarray] | np.ndarray,
    intrinsics: CameraIntrinsics,
    config: PnpConfig,
    rng: np.random.Generator,
    fallback: bool = True,
) -> RelativePose:
    """PnP seeded by poses found elsewhere (guided PnP), falling back to RANSAC.

    Each guess (4, 4) T_ref_from_query (e.g. another entry's hypothesis brought into this
    entry's frame; a list, or a (G, 4, 4) array) is scored on this entry's own M
    correspondences; the inliers of the guess with the most (the first of equals) are
    refit as RANSAC's inliers are (SQPnP, re-selection, LM), so the pose is the entry's
    own optimum, not the guess nudged. The result is kept when it has at least
    :func:`guided_min_inliers` inliers and passes the usual checks (``method`` is then
    "guided"); otherwise, or without guesses, the entry gets its own
    :func:`estimate_relative_pose`, unless ``fallback`` is False: then it is rejected
    (``method`` "guided"). Either way the pose comes from this entry's own
    correspondences only.
    """
    from monoloc.server.vision._pnp_kernel import best_guess_inliers

    pixels, points = _checked_correspondences(points_query_px, points_ref_cam)
    n_points = len(pixels)
    needed = guided_min_inliers(n_points, config)
    K = intrinsics.K
    best_count = -1
    min_count = max(_MIN_POINTS_FOR_SOLVER, config.guided_refit_min_fraction * needed)
    if len(guesses_T_ref_from_query) and n_points >= needed:
        guesses = np.ascontiguousarray(guesses_T_ref_from_query, dtype=np.float64)
        errors_px = np.empty(n_points)
        mask = np.empty(n_points, dtype=bool)
        _, best_count = best_guess_inliers(
            points, pixels, guesses.reshape(-1, 4, 4), K[0, 0], K[1, 1], K[0, 2], K[1, 2],
            config.reprojection_error_px, min_count, errors_px, mask,
        )  # fmt: skip
    if best_count >= min_count:
        # The guess only chooses the consensus set, as RANSAC's best sample does: the pose
        # is then this entry's own (SQPnP on that set, re-selection, LM), so it does not
        # stay anchored to the guess along directions this entry constrains poorly.
        try:
            R, t, mask, errors_px = _refit(points, pixels, mask, K, config)
        except cv2.error:
            R = None
        if R is not None and np.count_nonzero(mask) >= needed:
            T_ref_from_query = _ref_from_query(R, t)
            judged = _judged(T_ref_from_query, mask, errors_px, intrinsics, config, "guided")
            if judged.accepted:
                return judged
    if not fallback:
        return _rejected(
            n_points,
            f"the poses found so far keep {max(best_count, 0)} of {n_points} matches "
            f"(< {needed}); no own RANSAC once the pose is confirmed",
            method="guided",
        )
    return estimate_relative_pose(pixels, points, intrinsics, config, rng)
