"""An entry's image (the small JPEG the console shows) is stored with the entry, read
back unchanged, deleted with it, and refused when it is not a JPEG that fits."""

from dataclasses import replace

import cv2
import numpy as np
import pytest
from skimage import data as skdata
from sqlalchemy import func, select

from monoloc.core.camera import KITTI_CAM0
from monoloc.core.errors import InvalidInputError, NotFoundError
from monoloc.server.entry_builder import BuildConfig, entry_image
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.entries import add_entry, delete_entry, get_entry_image
from monoloc.server.storage.maps import delete_map
from monoloc.server.storage.models import EntryImage


def _kitti_sized_photo() -> np.ndarray:
    """A real photograph (scikit-image's camera man) at the KITTI camera's size."""
    size = (KITTI_CAM0.width_px, KITTI_CAM0.height_px)
    return cv2.resize(skdata.camera(), size, interpolation=cv2.INTER_AREA)


def test_entry_image_is_a_small_jpeg_of_the_photo():
    photo = _kitti_sized_photo()
    unmatched = np.array([[10.5, 20.25], [1200.0, 370.0]], np.float32)
    image = entry_image(photo, unmatched, BuildConfig(image_max_side_px=640))
    assert (image.width_px, image.height_px) == (640, round(376 * 640 / 1241))
    decoded = cv2.imdecode(np.frombuffer(image.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert decoded.shape == (image.height_px, image.width_px)
    small = cv2.resize(photo, (image.width_px, image.height_px), interpolation=cv2.INTER_AREA)
    assert np.abs(decoded.astype(float) - small).mean() < 4.0  # the same picture
    assert len(image.jpeg) < 60_000
    np.testing.assert_array_equal(image.keypoints_without_point_px, unmatched)
    assert entry_image(photo, unmatched, BuildConfig(image_max_side_px=0)) is None
    # a 16-bit source keeps its visible range instead of saturating
    deep = entry_image(photo.astype(np.uint16) * 200, unmatched, BuildConfig())
    decoded = cv2.imdecode(np.frombuffer(deep.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert decoded.max() - decoded.min() > 200


def test_image_is_stored_read_back_and_deleted_with_its_entry(factory, map_id, make_entry):
    image = entry_image(_kitti_sized_photo(), np.zeros((3, 2), np.float32), BuildConfig())
    with session_scope(factory) as session:
        with_image = add_entry(session, map_id, replace(make_entry("a"), image=image))[0]
        without = add_entry(session, map_id, make_entry("b"))[0]
    with session_scope(factory) as session:
        got = get_entry_image(session, with_image.id, map_id=map_id)
        assert got.jpeg == image.jpeg
        assert (got.width_px, got.height_px) == (image.width_px, image.height_px)
        np.testing.assert_array_equal(got.keypoints_without_point_px, np.zeros((3, 2)))
        assert get_entry_image(session, without.id) is None
        with pytest.raises(NotFoundError):
            get_entry_image(session, with_image.id, map_id=map_id + 1)
    with session_scope(factory) as session:
        delete_entry(session, with_image.id)
    with session_scope(factory) as session:
        assert session.scalar(select(func.count()).select_from(EntryImage)) == 0
        add_entry(session, map_id, replace(make_entry("c"), image=image))
    with session_scope(factory) as session:
        delete_map(session, map_id)
    with session_scope(factory) as session:
        assert session.scalar(select(func.count()).select_from(EntryImage)) == 0


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(jpeg=b"\x89PNG\r\n\x1a\n"), "must be a JPEG"),
        (dict(width_px=5000), "within the 1241x376 image"),
        (dict(height_px=0), "within the 1241x376 image"),
        (dict(keypoints_without_point_px=np.zeros((2, 3))), "keypoints_without_point_px"),
    ],
)
def test_a_bad_image_refuses_the_entry_and_stores_nothing(
    factory, map_id, make_entry, change, message
):
    image = entry_image(_kitti_sized_photo(), np.zeros((0, 2), np.float32), BuildConfig())
    with session_scope(factory) as session, pytest.raises(InvalidInputError, match=message):
        add_entry(session, map_id, replace(make_entry("bad"), image=replace(image, **change)))
    with session_scope(factory) as session:
        assert session.scalar(select(func.count()).select_from(EntryImage)) == 0
