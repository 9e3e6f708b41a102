"""`monoloc drive --image-format jpeg`: the vehicle re-encodes its recorded PNG frames as
JPEG (Pillow) and the live server localizes them as well as the PNGs; a quality out of
range is one error line and a non-zero exit before anything is sent."""

from __future__ import annotations

import numpy as np
import pytest
from e2e_helpers import printed_rmse_m, query_drive_args, run_monoloc

from monoloc.server.api import localizing


def _drive(live_map, out, *extra: str):
    return run_monoloc("drive", *query_drive_args(live_map, out), *extra)


@pytest.fixture
def decoded_kinds(monkeypatch) -> list[str]:
    """The format of every frame the live server decodes while the test runs."""
    kinds: list[str] = []
    original = localizing.decode_gray

    def recording(data, info, what):
        kinds.append(info.kind)
        return original(data, info, what)

    monkeypatch.setattr(localizing, "decode_gray", recording)
    return kinds


def test_a_drive_sent_as_jpeg_localizes_as_well_as_png(live_map, tmp_path, decoded_kinds):
    done = _drive(live_map, tmp_path / "jpeg" / "query", "--image-format", "jpeg")
    assert done.returncode == 0, done.stderr
    assert "frames sent as JPEG quality 90" in done.stderr
    assert decoded_kinds and set(decoded_kinds) == {"jpeg"}
    rmse = printed_rmse_m(done.stdout)
    assert rmse < 0.5
    tum = np.loadtxt(tmp_path / "jpeg" / "query.tum.txt")
    assert len(tum) >= 16
    decoded_kinds.clear()
    png = _drive(live_map, tmp_path / "png" / "query")
    assert png.returncode == 0, png.stderr
    assert set(decoded_kinds) == {"png"}
    png_rmse = printed_rmse_m(png.stdout)
    assert rmse <= png_rmse + 0.05


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (("--image-format", "jpeg", "--jpeg-quality", "0"), "JPEG quality must be within 1-95"),
        (("--image-format", "webp"), "image format must be one of recorded, jpeg"),
    ],
)
def test_a_bad_image_format_is_one_line_and_nothing_is_sent(
    live_map, tmp_path, decoded_kinds, extra, message
):
    done = _drive(live_map, tmp_path / "bad" / "query", *extra)
    assert done.returncode == 1
    assert done.stderr.strip().splitlines()[-1].startswith(f"error: {message}")
    assert decoded_kinds == []
    assert not (tmp_path / "bad").exists()
