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


def test_invalid_config_raises_on_the_grid_too():
    with pytest.raises(InvalidInputError):
        OrbConfig(grid_cells=(0, 4))
    with pytest.raises(InvalidInputError):
        OrbConfig(candidates_factor=0.5)
    assert OrbConfig(grid_cells=None).n_candidates == 1000
    assert OrbConfig().n_candidates == 2000
    for low in (0, 21):
        with pytest.raises(InvalidInputError):
            OrbConfig(min_fast_threshold=low)
    with pytest.raises(InvalidInputError):
        OrbConfig(flat_fast_corners=0)


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

    config = OrbConfig(grid_cells=None)  # ORB's own keypoints, one to one
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
    # spread over the grid: the kept keypoints are ORB's candidates picked by the grid,
    # each with its own scale
    spread = extract_features(image, OrbConfig(), scales=True)
    candidates, _ = _create_orb(OrbConfig(), OrbConfig().n_candidates).detectAndCompute(
        blurred, None
    )
    picked = _picked(candidates, image.shape)
    assert np.array_equal(cv2.KeyPoint_convert(candidates)[picked], spread.keypoints_px)
    sizes = np.array([candidates[i].size for i in picked])
    assert np.allclose(spread.scales * config.edge_threshold, sizes, rtol=1e-5)


def _picked(keypoints, image_shape) -> np.ndarray:
    import cv2

    from monoloc.server.vision.features import spread_over_grid

    response = np.array([k.response for k in keypoints])
    config = OrbConfig()
    points = cv2.KeyPoint_convert(keypoints)
    return spread_over_grid(points, response, image_shape, config.grid_cells, config.max_features)


def _shaded_half(image: np.ndarray) -> np.ndarray:
    """The photograph with its left half in the shade: a third of the contrast, darker."""
    shaded = image.astype(np.float64)
    half = image.shape[1] // 2
    shaded[:, :half] = 20.0 + shaded[:, :half] / 3.0
    return shaded.astype(np.uint8)


def test_the_grid_keeps_corners_in_the_shade_that_the_strongest_rule_drops():
    """A real photograph with one half in the shade: ORB's strongest 1000 (the paper's
    rule) sit nearly all in the sunlit half, the grid keeps several times as many in the
    shade, and every kept feature is one of ORB's own candidates with its descriptor."""
    import cv2

    image = _shaded_half(data.astronaut()[:, :, 1])
    half = image.shape[1] // 2
    strongest = extract_features(image, OrbConfig(grid_cells=None))
    spread = extract_features(image)
    assert len(strongest) == len(spread) == 1000
    shade_strongest = np.mean(strongest.keypoints_px[:, 0] < half)
    shade_spread = np.mean(spread.keypoints_px[:, 0] < half)
    # 4 % and 23 % here: the candidates are ORB's strongest 2000, few of them in the shade
    assert shade_strongest < 0.1 and shade_spread > max(0.15, 3 * shade_strongest)
    config = OrbConfig()
    blurred = cv2.GaussianBlur(image, (config.blur_ksize, config.blur_ksize), 0)
    keypoints, descriptors = _create_orb(config, config.n_candidates).detectAndCompute(
        blurred, None
    )
    picked = _picked(keypoints, image.shape)
    assert np.array_equal(cv2.KeyPoint_convert(keypoints)[picked], spread.keypoints_px)
    assert np.array_equal(descriptors[picked], spread.descriptors)


def test_a_flat_lit_image_is_described_at_the_low_fast_threshold():
    """A real photograph at half its contrast (flat light) has fewer than 150 FAST corners
    at 20 (ORB finds about 600 over its pyramid): it is described at the low threshold,
    1000 of ORB's own candidates there with their descriptors (with the older rule too:
    fewer than 1000 ORB corners at 20, detected again); a photograph with enough corners
    is described exactly as with one threshold."""
    import cv2

    image = (64 + data.camera().astype(np.float64) / 2).astype(np.uint8)
    config = OrbConfig()
    blurred = cv2.GaussianBlur(image, (config.blur_ksize, config.blur_ksize), 0)
    assert len(cv2.FastFeatureDetector_create(20).detect(blurred)) < config.flat_fast_corners
    one_threshold = extract_features(image, OrbConfig(min_fast_threshold=None))
    low = OrbConfig(fast_threshold=config.min_fast_threshold)
    keypoints, descriptors = _create_orb(low, config.n_candidates).detectAndCompute(blurred, None)
    picked = _picked(keypoints, image.shape)
    for rule in (config, OrbConfig(flat_fast_corners=None)):
        two_level = extract_features(image, rule)
        assert len(one_threshold) < 700 and len(two_level) == config.max_features
        assert np.array_equal(cv2.KeyPoint_convert(keypoints)[picked], two_level.keypoints_px)
        assert np.array_equal(descriptors[picked], two_level.descriptors)
    textured = data.camera()
    a = extract_features(textured)
    b = extract_features(textured, OrbConfig(min_fast_threshold=None))
    assert np.array_equal(a.keypoints_px, b.keypoints_px)
    assert np.array_equal(a.descriptors, b.descriptors)


def test_spread_over_grid_takes_every_cells_strongest_first():
    from monoloc.server.vision.features import spread_over_grid

    rng = np.random.default_rng(3)
    points = rng.uniform([0, 0], [400, 200], size=(500, 2)).astype(np.float32)
    points[:300] = rng.uniform([0, 0], [100, 100], size=(300, 2))  # a crowded corner cell
    response = rng.uniform(size=500)
    response[:300] += 10.0  # ... that is also the brightest
    kept = spread_over_grid(points, response, (200, 400), (4, 2), 8)
    cells = (points[kept, 1] // 100).astype(int) * 4 + (points[kept, 0] // 100).astype(int)
    assert sorted(cells.tolist()) == list(range(8))  # one per cell, not eight in the corner
    for i, c in zip(kept, cells, strict=True):
        in_cell = ((points[:, 1] // 100) * 4 + points[:, 0] // 100) == c
        assert response[i] == response[in_cell].max()
    assert np.all(np.diff(kept) > 0)  # in ORB's order
    # more than the cells hold in one turn: the second turn, then all there are
    assert len(spread_over_grid(points, response, (200, 400), (4, 2), 16)) == 16
    assert len(spread_over_grid(points, response, (200, 400), (4, 2), 900)) == 500
