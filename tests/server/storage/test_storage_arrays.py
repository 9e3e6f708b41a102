import numpy as np
import pytest
from sqlalchemy import update

from monoloc.core.errors import InvalidInputError
from monoloc.server.storage import arrays as arr
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.entries import add_entry, get_entry_data, iter_map_vectors
from monoloc.server.storage.models import Entry


@pytest.mark.parametrize(
    ("spec", "shape", "dtype"),
    [
        (arr.POSE, (4, 4), np.float64),
        (arr.VLAD, (2048,), np.float32),
        (arr.CODE, (256,), np.uint8),
        (arr.KEYPOINTS, (7, 2), np.float32),
        (arr.DESCRIPTORS, (7, 32), np.uint8),
        (arr.POINTS, (0, 3), np.float32),
        (arr.CENTRES, (64, 32), np.float32),
    ],
)
def test_pack_unpack_round_trip_is_exact(spec, shape, dtype):
    rng = np.random.default_rng(3)
    if np.dtype(dtype).kind == "u":
        a = rng.integers(0, 256, shape).astype(dtype)
    else:
        a = (rng.normal(size=shape) * 10.0 ** rng.integers(-30, 30, shape)).astype(dtype)
    back = arr.unpack_array(arr.pack_array(a, spec, "x"), spec, "x")
    assert back.dtype == dtype and back.shape == shape
    assert np.array_equal(back.view(np.uint8), a.view(np.uint8))  # bit-exact


def test_big_endian_input_is_stored_little_endian():
    a = np.arange(8, dtype=">f4").reshape(4, 2)
    blob = arr.pack_array(a, arr.KEYPOINTS, "kp")
    assert blob == np.arange(8, dtype="<f4").tobytes()
    assert np.array_equal(arr.unpack_array(blob, arr.KEYPOINTS, "kp"), a)


@pytest.mark.parametrize(
    ("value", "spec", "message"),
    [
        (np.zeros(2047, np.float32), arr.VLAD, "shape"),
        (np.zeros((5, 3), np.float32), arr.KEYPOINTS, "shape"),
        (np.full(2048, np.nan, np.float32), arr.VLAD, "NaN"),
        (np.full((2, 32), 300), arr.DESCRIPTORS, "outside the range"),
        (np.zeros((2, 32), np.float32), arr.DESCRIPTORS, "integer"),
    ],
)
def test_pack_rejects_wrong_arrays(value, spec, message):
    with pytest.raises(InvalidInputError, match=message):
        arr.pack_array(value, spec, "column")


def test_unpack_rejects_corrupt_blobs():
    with pytest.raises(InvalidInputError, match="corrupt blob v: 8191 bytes, expected 8192"):
        arr.unpack_array(b"\0" * 8191, arr.VLAD, "v")
    with pytest.raises(InvalidInputError, match="not a multiple of 12"):
        arr.unpack_array(b"\0" * 13, arr.POINTS, "p")
    with pytest.raises(InvalidInputError, match="missing"):
        arr.unpack_array(None, arr.POSE, "T")


def test_stored_entry_arrays_round_trip_and_corrupt_blob_raises(factory, map_id, make_entry):
    new = make_entry("frame-0", x_m=3.0, y_m=-2.0, yaw_rad=1.0)
    with session_scope(factory) as session:
        entry_id = add_entry(session, map_id, new)[0].id
    with session_scope(factory) as session:
        (data,) = get_entry_data(session, [entry_id])
    assert np.array_equal(data.vlad, new.vlad)
    assert np.array_equal(data.code, new.code)
    assert np.array_equal(data.keypoints_px, new.keypoints_px)
    assert np.array_equal(data.descriptors, new.descriptors)
    assert np.array_equal(data.points_cam, new.points_cam)
    assert np.array_equal(data.T_world_from_cam, new.T_world_from_cam)
    assert data.summary.x_m == pytest.approx(3.0) and data.summary.yaw_rad == pytest.approx(1.0)

    with session_scope(factory) as session:
        session.execute(update(Entry).where(Entry.id == entry_id).values(vlad=b"\0" * 100))
    with session_scope(factory) as session:
        with pytest.raises(InvalidInputError, match=f"entries id={entry_id} vlad"):
            get_entry_data(session, [entry_id])
        with pytest.raises(InvalidInputError, match="corrupt blob"):
            list(iter_map_vectors(session, map_id))
