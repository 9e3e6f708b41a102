import numpy as np
import pytest
from skimage import data

from monoloc.core.errors import InvalidInputError
from monoloc.server.vision.features import OrbConfig, _create_orb, extract_features


def test_real_photo_gives_1000_features_with_documented_shapes():
    features = extract_features(data.camera())
    assert features.keypoints_px.shape == (1000, 2) and features.keypoints_px.dtype == np.float32
    assert features.descriptors.shape == (1000, 32) and features.descriptors.dtype == np.uint8
    height, width = data.camera().shape
    assert np.all(features.keypoints_px >= 0)
    assert np.all(features.keypoints_px[:, 0] < width) and np.all(
        features.keypoints_px[:, 1] < height
    )


def test_max_features_is_respected_and_is_deterministic():
    image = data.brick()
    a = extract_features(image, OrbConfig(max_features=200))
    b = extract_features(image, OrbConfig(max_features=200))
    assert len(a) == 200
    assert np.array_equal(a.descriptors, b.descriptors)
    assert np.array_equal(a.keypoints_px, b.keypoints_px)


def test_colour_input_equals_its_gray_conversion():
    import cv2

    rgb = data.astronaut()
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    assert np.array_equal(extract_features(rgb).descriptors, extract_features(gray).descriptors)


def test_blur_changes_the_features():
    image = data.camera()
    blurred = extract_features(image)
    raw = extract_features(image, OrbConfig(blur_ksize=1))
    assert not np.array_equal(blurred.keypoints_px, raw.keypoints_px)


@pytest.mark.parametrize("shape", [(0, 0), (40, 0), (240, 320)])
def test_empty_or_flat_images_give_zero_features_with_right_shapes(shape):
    features = extract_features(np.full(shape, 128, dtype=np.uint8))
    assert features.keypoints_px.shape == (0, 2) and features.keypoints_px.dtype == np.float32
    assert features.descriptors.shape == (0, 32) and features.descriptors.dtype == np.uint8


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((64, 64), dtype=np.float32),
        np.zeros((64, 64), dtype=np.uint16),
        np.zeros((64, 64, 4), dtype=np.uint8),
        np.zeros((2, 64, 64, 3), dtype=np.uint8),
        np.zeros(64, dtype=np.uint8),
    ],
)
def test_wrong_dtype_or_shape_raises(image):
    with pytest.raises(InvalidInputError):
        extract_features(image)


def test_invalid_config_raises():
    with pytest.raises(InvalidInputError):
        OrbConfig(blur_ksize=4)
    with pytest.raises(InvalidInputError):
        OrbConfig(max_features=0)


def test_concurrent_calls_give_the_serial_result():
    from concurrent.futures import ThreadPoolExecutor

    images = [data.camera(), data.brick(), data.coins(), data.moon()] * 2
    serial = [extract_features(image).descriptors for image in images]
    with ThreadPoolExecutor(max_workers=4) as pool:
        parallel = list(pool.map(lambda image: extract_features(image).descriptors, images))
    assert all(np.array_equal(a, b) for a, b in zip(serial, parallel, strict=True))


def test_describe_keypoints_reproduces_orb_at_its_own_full_resolution_detections():
    """ORB described at given pixels (a reconstruction's observations) equals ORB's own
    description of the keypoints it detected there at pyramid level 0; a point closer to
    the border than ORB's patch is dropped."""
    import cv2

    from monoloc.server.vision.features import _create_orb, describe_keypoints

    image = data.camera()
    config = OrbConfig()
    blurred = cv2.GaussianBlur(image, (config.blur_ksize, config.blur_ksize), 0)
    keypoints, descriptors = _create_orb(config).detectAndCompute(blurred, None)
    level0 = [i for i, k in enumerate(keypoints) if k.octave == 0]
    assert len(level0) > 100
    pixels = np.array([keypoints[i].pt for i in level0] + [[3.0, 3.0]])
    kept, described = describe_keypoints(image, pixels, config)
    assert kept[:-1].all() and not kept[-1]
    differing_bits = np.unpackbits(described ^ descriptors[level0], axis=1).sum(axis=1)
    assert np.mean(differing_bits == 0) > 0.95 and differing_bits.max() <= 4


def test_scales_are_the_pyramid_scale_opencv_detected_each_keypoint_at():
    import cv2

    config = OrbConfig()
    image = data.camera()
    assert extract_features(image, config).scales is None  # only when asked for
    features = extract_features(image, config, scales=True)
    assert features.scales.shape == (len(features),) and features.scales.dtype == np.float32
    # OpenCV's ORB gives a keypoint found on level L the size patch_size * scale_factor ** L.
    blurred = cv2.GaussianBlur(image, (config.blur_ksize, config.blur_ksize), 0)
    keypoints, _ = _create_orb(config).detectAndCompute(blurred, None)
    assert np.allclose(cv2.KeyPoint_convert(keypoints), features.keypoints_px)
    sizes = np.array([k.size for k in keypoints])
    assert np.allclose(features.scales * config.edge_threshold, sizes, rtol=1e-5)
    levels = np.round(np.log(features.scales) / np.log(config.scale_factor))
    assert levels.min() == 0 and levels.max() >= 4  # a photograph has corners at every scale
    assert extract_features(np.full((64, 64), 9, dtype=np.uint8)).scales.shape == (0,)
