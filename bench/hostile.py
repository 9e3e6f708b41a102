"""What a hostile frame costs the server's decoding, next to a real frame and to the plain
decoder on the same bytes (issue 15, finding 1: a camera-sized PNG whose data inflates to
gigabytes cost 16.9 s of CPU through ``cv2.imdecode``).

The bomb: a PNG whose header declares the KITTI camera's 1241 x 376 gray image and whose
IDAT stream inflates to ``--inflate-mb`` MB of zeros (~1000:1, about 4 MB on the wire at
4 GB). The server's path is the localize route's: ``check_image`` (header) then
``decode_gray`` (the IDAT inflated up to what the header needs, then OpenCV). The baseline
is ``cv2.imdecode`` of the same bytes, as before the fix (run once; ``--no-baseline``
skips it). A real frame: a 1241 x 376 photograph-like PNG (scikit-image's camera,
resized), decoded through the same path and by ``cv2.imdecode`` alone (the server's path
inflates the data once, then hands OpenCV the scanlines in stored deflate blocks).
Figures are CPU seconds (process time, one thread). Usage:
    python -m bench.hostile [--inflate-mb 4096] [--no-baseline]
"""

from __future__ import annotations

import argparse
import json
import struct
import time
import zlib
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).parent / "results"
WIDTH_PX, HEIGHT_PX = 1241, 376


def _chunk(kind: bytes, payload: bytes) -> bytes:
    crc = zlib.crc32(kind + payload) & 0xFFFFFFFF
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)


def bomb_png(inflate_mb: int) -> bytes:
    """Camera-sized 8-bit gray PNG header, IDAT inflating to ``inflate_mb`` MB of zeros."""
    deflate = zlib.compressobj(9)
    block = bytes(1 << 20)
    stream = b"".join(deflate.compress(block) for _ in range(inflate_mb)) + deflate.flush()
    ihdr = struct.pack(">IIBBBBB", WIDTH_PX, HEIGHT_PX, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", ihdr)
        + _chunk(b"IDAT", stream)
        + _chunk(b"IEND", b"")
    )


def real_png() -> bytes:
    import cv2
    from skimage import data

    gray = cv2.resize(data.camera(), (WIDTH_PX, HEIGHT_PX), interpolation=cv2.INTER_AREA)
    return cv2.imencode(".png", gray)[1].tobytes()


def cpu_s(fn, repeat: int) -> tuple[float, str]:
    """Median process-CPU seconds of ``fn()`` over ``repeat`` calls, and its outcome."""
    times, outcome = [], ""
    for _ in range(repeat):
        start = time.process_time()
        try:
            result = fn()
            outcome = f"decoded {getattr(result, 'shape', None)}"
        except Exception as exc:  # the outcome is reported, whatever it is
            outcome = f"refused: {type(exc).__name__}: {str(exc)[:90]}"
        times.append(time.process_time() - start)
    return float(np.median(times)), outcome


def main() -> None:
    import cv2

    from monoloc.server.api.limits import check_image, decode_gray

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--inflate-mb", type=int, default=4096)
    parser.add_argument("--no-baseline", action="store_true")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    bomb, real = bomb_png(args.inflate_mb), real_png()

    def server_path(data: bytes):
        info = check_image(data, "image", 10_000_000)
        return decode_gray(data, info, "image")

    real_buffer = np.frombuffer(real, np.uint8)
    rows = {
        "real frame, server path": cpu_s(lambda: server_path(real), 20),
        # the decoder alone, unguarded: what the guard's own inflation costs on top of it
        "real frame, cv2.imdecode alone": cpu_s(
            lambda: cv2.imdecode(real_buffer, cv2.IMREAD_GRAYSCALE), 20
        ),
        "bomb, server path": cpu_s(lambda: server_path(bomb), 5),
    }
    if not args.no_baseline:
        buffer = np.frombuffer(bomb, np.uint8)
        rows["bomb, cv2.imdecode (before the fix)"] = cpu_s(
            lambda: cv2.imdecode(buffer, cv2.IMREAD_GRAYSCALE), 1
        )
    print(
        f"bomb: {len(bomb) / 1e6:.1f} MB on the wire, inflating to {args.inflate_mb} MB; "
        f"real frame {len(real) / 1e3:.0f} kB"
    )
    for name, (seconds, outcome) in rows.items():
        print(f"  {name:<38} {1e3 * seconds:9.1f} ms CPU  {outcome}")
    ratio = rows["bomb, server path"][0] / rows["real frame, server path"][0]
    print(f"  bomb / real frame through the server's path: {ratio:.2f}x")
    RESULTS.mkdir(exist_ok=True)
    out = {
        "bomb_bytes": len(bomb),
        "inflate_mb": args.inflate_mb,
        "real_bytes": len(real),
        "cpu_ms": {name: 1e3 * s for name, (s, _) in rows.items()},
        "outcome": {name: o for name, (_, o) in rows.items()},
    }
    (RESULTS / "hostile.json").write_text(json.dumps(out, indent=2))
    print(f"wrote {RESULTS / 'hostile.json'}")


if __name__ == "__main__":
    main()
