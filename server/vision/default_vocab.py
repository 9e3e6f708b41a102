"""Training set and recipe of the shipped default vocabulary (data/default_vocabulary.*).

The set is ORB descriptors (the same blur + ORB as every query) of real photographs that
ship with scikit-image, so it is reproducible offline. Each photograph, in grayscale, is
augmented by scale, rotation and crops. Retrain with
``monoloc vocab train --out server/vision/data/default_vocabulary.npz``.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from monoloc.server.vision.features import OrbConfig, as_gray_uint8, extract_features
from monoloc.server.vision.vocabulary import Vocabulary, VocabularyConfig, train_vocabulary

# scikit-image photographs available without a download (skimage.data).
DEFAULT_PHOTOS = (
    "astronaut",
    "brick",
    "camera",
    "coffee",
    "chelsea",
    "rocket",
    "text",
    "gravel",
    "grass",
    "coins",
    "moon",
    "page",
    "horse",
    "clock",
    "immunohistochemistry",
    "hubble_deep_field",
    "cell",
    "stereo_motorcycle",
    "cat",
    "retina",
)


@dataclass(frozen=True)
class TrainingSetConfig:
    """Augmentations of each photo: every scale, then at each scale every rotation (90
    degree steps exactly, others followed by the largest centred square without borders)
    and ``crops_per_scale`` random crops of ``crop_fraction`` of each side."""

    photos: tuple[str, ...] = DEFAULT_PHOTOS
    scales: tuple[float, ...] = (0.5, 0.75, 1.0, 1.5, 2.0)
    rotations_deg: tuple[float, ...] = (0.0, 90.0, 20.0, -35.0)
    crops_per_scale: int = 3
    crop_fraction: float = 0.6
    seed: int = 0
    orb: OrbConfig = OrbConfig()


def load_photos(names: tuple[str, ...]) -> list[tuple[str, np.ndarray]]:
    """The named ``skimage.data`` photographs as (name, (H, W) uint8 gray) pairs; the stereo
    pair gives two images."""
    from skimage import data

    photos = []
    for name in names:
        loaded = getattr(data, name)()
        images = loaded[:2] if isinstance(loaded, tuple) else (loaded,)
        for i, image in enumerate(images):
            image = np.asarray(image)
            if image.dtype == bool:
                image = image.astype(np.uint8) * 255
            if image.ndim == 3 and image.shape[2] == 4:
                image = image[:, :, :3]
            photos.append(
                (f"{name}{'_' + str(i) if len(images) > 1 else ''}", as_gray_uint8(image))
            )
    return photos


def _rotated(image: np.ndarray, angle_deg: float) -> np.ndarray:
    import cv2

    quarter_turns = angle_deg / 90.0
    if quarter_turns == round(quarter_turns):
        return np.ascontiguousarray(np.rot90(image, int(round(quarter_turns))))
    h, w = image.shape
    M = cv2.getRotationMatrix2D(((w - 1) / 2.0, (h - 1) / 2.0), angle_deg, 1.0)
    turned = cv2.warpAffine(image, M, (w, h), flags=cv2.INTER_LINEAR)
    theta = np.radians(abs(angle_deg))
    side = int(min(h, w) / (abs(np.cos(theta)) + abs(np.sin(theta))))
    top, left = (h - side) // 2, (w - side) // 2
    return np.ascontiguousarray(turned[top : top + side, left : left + side])


def augmented_images(
    photo: np.ndarray, config: TrainingSetConfig, rng: np.random.Generator
) -> Iterator[np.ndarray]:
    """Yield the augmented (H, W) uint8 versions of one gray photo."""
    import cv2

    for scale in config.scales:
        h, w = photo.shape
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        interp = cv2.INTER_AREA if scale < 1.0 else cv2.INTER_LINEAR
        scaled = photo if scale == 1.0 else cv2.resize(photo, size, interpolation=interp)
        for angle in config.rotations_deg:
            yield _rotated(scaled, angle)
        ch, cw = (
            int(scaled.shape[0] * config.crop_fraction),
            int(scaled.shape[1] * config.crop_fraction),
        )
        for _ in range(config.crops_per_scale):
            top = int(rng.integers(0, scaled.shape[0] - ch + 1))
            left = int(rng.integers(0, scaled.shape[1] - cw + 1))
            yield np.ascontiguousarray(scaled[top : top + ch, left : left + cw])


def build_training_set(config: TrainingSetConfig = TrainingSetConfig()) -> tuple[np.ndarray, int]:
    """ORB descriptors of every augmented photo: ((N, 32) uint8, number of images)."""
    rng = np.random.default_rng(config.seed)
    descriptor_sets, n_images = [], 0
    for _, photo in load_photos(config.photos):
        for image in augmented_images(photo, config, rng):
            descriptor_sets.append(extract_features(image, config.orb).descriptors)
            n_images += 1
    return np.concatenate(descriptor_sets), n_images


def train_default_vocabulary(
    training: TrainingSetConfig = TrainingSetConfig(),
    vocabulary: VocabularyConfig = VocabularyConfig(),
) -> Vocabulary:
    """Build the training set and run k-means: the recipe of the shipped vocabulary."""
    descriptors, n_images = build_training_set(training)
    description = (
        f"monoloc default vocabulary: FAISS k-means (k={vocabulary.n_words}, "
        f"niter={vocabulary.n_iter}, seed={vocabulary.seed}) on {len(descriptors)} ORB "
        f"descriptors (blur {training.orb.blur_ksize}x{training.orb.blur_ksize}, "
        f"{training.orb.max_features} features) of {n_images} augmented grayscale "
        f"scikit-image photographs ({len(training.photos)} photos; scales {training.scales}, "
        f"rotations {training.rotations_deg} deg, {training.crops_per_scale} crops of "
        f"{training.crop_fraction} per scale, seed {training.seed}); see default_vocabulary.md"
    )
    return train_vocabulary(descriptors, vocabulary, description=description)
