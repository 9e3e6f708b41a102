"""``camera.yaml``: a camera in ROS's calibration file layout, beside a run's frames.

What ROS's camera_calibration / camera_info_manager write (and ``sensor_msgs/CameraInfo``
names the same fields)::

    image_width: 1024
    image_height: 576
    camera_name: fleet_front
    camera_matrix: {rows: 3, cols: 3, data: [fx, 0, cx, 0, fy, cy, 0, 0, 1]}
    distortion_model: plumb_bob
    distortion_coefficients: {rows: 1, cols: 5, data: [k1, k2, p1, p2, k3]}
    rectification_matrix: {rows: 3, cols: 3, data: [...]}
    projection_matrix: {rows: 3, cols: 4, data: [...]}

Read: the image size (``image_width``/``image_height``, or CameraInfo's ``width``/
``height``), K (``camera_matrix`` or CameraInfo's ``K``/``k``, 9 values), the lens
(``distortion_model`` with ``distortion_coefficients`` or ``D``/``d``; an unknown model
is refused naming it), and where the camera sits on the vehicle when the file says:
``T_vehicle_from_cam`` (4x4, ``{rows, cols, data}`` or rows) or a ``mounting`` mapping of
:class:`monoloc.core.mounting.CameraMounting`'s fields (monoloc's extension; ROS's own
tools ignore unknown keys).

The client reads it without a YAML library (``monoloc drive`` on the light install):
:func:`parse_simple_yaml` takes the subset these files use (block mappings by
indentation, flow lists and flow mappings of scalars, block lists of scalars, comments).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from monoloc.core.camera import CameraIntrinsics, LensDistortion
from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.mounting import CameraMounting

CAMERA_YAML = "camera.yaml"


@dataclass(frozen=True)
class CameraFile:
    """A run's camera as its file says: intrinsics and, when given, the mounting."""

    path: Path
    intrinsics: CameraIntrinsics
    mounting: CameraMounting | None = None
    name: str | None = None


# ---- the YAML subset ----------------------------------------------------------------


def _scalar(text: str) -> Any:
    text = text.strip()
    if not text:
        return None
    if text[0] in "'\"" and text[-1] == text[0] and len(text) >= 2:
        return text[1:-1]
    lowered = text.lower()
    if lowered in ("null", "~"):
        return None
    if lowered in ("true", "false"):
        return lowered == "true"
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def _split_flow(body: str) -> list[str]:
    """Items of a flow collection's body at depth 0 (commas inside [] {} quotes kept)."""
    items, depth, quote, start = [], 0, None, 0
    for i, ch in enumerate(body):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            items.append(body[start:i])
            start = i + 1
    items.append(body[start:])
    return [item for item in items if item.strip()]


def _value(text: str) -> Any:
    text = text.strip()
    if text.startswith("["):
        if not text.endswith("]"):
            raise ValueError(f"unclosed flow list {text[:40]!r}")
        return [_value(item) for item in _split_flow(text[1:-1])]
    if text.startswith("{"):
        if not text.endswith("}"):
            raise ValueError(f"unclosed flow mapping {text[:40]!r}")
        out = {}
        for item in _split_flow(text[1:-1]):
            key, sep, rest = item.partition(":")
            if not sep:
                raise ValueError(f"flow mapping item without ':' {item.strip()!r}")
            out[key.strip().strip("'\"")] = _value(rest)
        return out
    return _scalar(text)


def _strip_comment(line: str) -> str:
    quote = None
    for i, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1] in " \t"):
            return line[:i]
    return line


def _logical_lines(text: str) -> list[tuple[int, str]]:
    """(indent, content) of each non-empty line, a flow collection spanning lines joined."""
    out: list[tuple[int, str]] = []
    pending: tuple[int, str] | None = None
    depth = 0
    for raw in text.splitlines():
        if raw.startswith(("%YAML", "---")) or raw.strip() == "...":
            continue
        line = _strip_comment(raw).rstrip()
        if not line.strip():
            continue
        if "\t" in line[: len(line) - len(line.lstrip())]:
            raise ValueError("tabs are not allowed for indentation")
        if pending is None:
            pending = (len(line) - len(line.lstrip()), line.strip())
        else:
            pending = (pending[0], pending[1] + " " + line.strip())
        depth += line.count("[") + line.count("{") - line.count("]") - line.count("}")
        if depth <= 0:
            out.append(pending)
            pending, depth = None, 0
    if pending is not None:
        raise ValueError(f"unclosed flow collection: {pending[1][:40]!r}")
    return out


def parse_simple_yaml(text: str) -> dict[str, Any]:
    """The YAML subset of camera files as a dict (ValueError when it is not in it)."""
    lines = _logical_lines(text)

    def block(i: int, indent: int) -> tuple[Any, int]:
        if lines[i][1].startswith("- ") or lines[i][1] == "-":
            items = []
            while i < len(lines) and lines[i][0] == indent and lines[i][1].startswith("-"):
                items.append(_value(lines[i][1][1:]))
                i += 1
            return items, i
        mapping: dict[str, Any] = {}
        while i < len(lines) and lines[i][0] == indent:
            content = lines[i][1]
            match = re.match(r"""^("[^"]*"|'[^']*'|[^:#]+?)\s*:(\s+|$)(.*)$""", content)
            if match is None:
                raise ValueError(f"expected 'key: value', got {content[:60]!r}")
            key, rest = match.group(1).strip("'\""), match.group(3)
            i += 1
            if rest.strip():
                mapping[key] = _value(rest)
            elif i < len(lines) and (
                lines[i][0] > indent or (lines[i][0] == indent and lines[i][1].startswith("-"))
            ):
                mapping[key], i = block(i, lines[i][0])
            else:
                mapping[key] = None
        return mapping, i

    if not lines:
        return {}
    if len(lines) == 1 and lines[0][1].startswith("{"):  # one flow mapping
        data, end = _value(lines[0][1]), 1
    else:
        data, end = block(0, lines[0][0])
    if end != len(lines):
        raise ValueError(f"unexpected indentation at {lines[end][1][:60]!r}")
    if not isinstance(data, dict):
        raise ValueError("a camera file must be a mapping at the top")
    return data


# ---- camera.yaml --------------------------------------------------------------------


def _numbers(value: Any, n: int | tuple[int, ...], what: str) -> list[float]:
    if isinstance(value, dict):
        value = value.get("data")
    flat = np.asarray(value, dtype=np.float64).ravel() if value is not None else np.zeros(0)
    sizes = (n,) if isinstance(n, int) else n
    if flat.size not in sizes:
        raise InvalidInputError(f"{what} must hold {' or '.join(map(str, sizes))} numbers")
    if not np.all(np.isfinite(flat)):
        raise InvalidInputError(f"{what} must be finite numbers")
    return [float(v) for v in flat]


def _first(data: dict, *names: str) -> Any:
    for name in names:
        if name in data and data[name] is not None:
            return data[name]
    return None


def camera_from_mapping(data: dict, path: Path) -> CameraFile:
    """A CameraFile from a camera.yaml's (or CameraInfo-like JSON's) fields."""
    try:
        width = _first(data, "image_width", "width", "width_px")
        height = _first(data, "image_height", "height", "height_px")
        if width is None or height is None:
            raise InvalidInputError("needs image_width and image_height")
        K_value = _first(data, "camera_matrix", "K", "k")
        if K_value is None:
            raise InvalidInputError("needs camera_matrix (or K): the 3x3 camera matrix")
        K = _numbers(K_value, 9, "camera_matrix")
        model = _first(data, "distortion_model")
        coefficients = _first(data, "distortion_coefficients", "D", "d")
        if isinstance(coefficients, dict):
            coefficients = coefficients.get("data")
        if coefficients is not None:
            coefficients = _numbers(coefficients, tuple(range(0, 15)), "distortion coefficients")
        lens = LensDistortion.parse(model, coefficients)
        if not (float(width) == int(width) and float(height) == int(height)):
            raise InvalidInputError(f"image size must be whole pixels, got {width}x{height}")
        intrinsics = CameraIntrinsics(K[0], K[4], K[2], K[5], int(width), int(height), lens)
        mounting = None
        if data.get("T_vehicle_from_cam") is not None:
            mounting = CameraMounting.from_dict({"T_vehicle_from_cam": data["T_vehicle_from_cam"]})
        elif data.get("mounting") is not None:
            mounting = CameraMounting.from_dict(data["mounting"])
    except (InvalidInputError, TypeError, ValueError) as exc:
        raise InputFileError(path, str(exc)) from exc
    name = data.get("camera_name")
    return CameraFile(path, intrinsics, mounting, None if name is None else str(name))


def read_camera_yaml(path: str | os.PathLike) -> CameraFile:
    """A camera.yaml (module docstring); InputFileError naming the file and the problem."""
    path = Path(path)
    try:
        data = parse_simple_yaml(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputFileError(path, f"cannot read the camera file: {exc}") from exc
    return camera_from_mapping(data, path)


def _flow(values) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def _matrix(name: str, rows: int, cols: int, values) -> list[str]:
    return [f"{name}:", f"  rows: {rows}", f"  cols: {cols}", f"  data: {_flow(values)}"]


def write_camera_yaml(
    path: str | os.PathLike,
    intrinsics: CameraIntrinsics,
    mounting: CameraMounting | np.ndarray | None = None,
    camera_name: str = "camera",
) -> Path:
    """Write ``intrinsics`` (and where the camera sits, ``T_vehicle_from_cam``) in ROS's
    calibration layout; a pinhole camera is plumb_bob with zero coefficients, as ROS
    writes it. Returns the path."""
    if not re.fullmatch(r"[A-Za-z0-9_.\-]+", camera_name):
        raise InvalidInputError(
            f"camera_name must be letters, digits, '_', '.', '-': {camera_name!r}"
        )
    k, lens = intrinsics, intrinsics.distortion
    model = "plumb_bob" if lens is None else lens.model
    D = [0.0] * 5 if lens is None else list(lens.coefficients)
    P = [k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    lines = [
        f"image_width: {int(k.width_px)}",
        f"image_height: {int(k.height_px)}",
        f"camera_name: {camera_name}",
        *_matrix("camera_matrix", 3, 3, k.K.ravel()),
        f"distortion_model: {model}",
        *_matrix("distortion_coefficients", 1, len(D), D),
        *_matrix("rectification_matrix", 3, 3, np.eye(3).ravel()),
        *_matrix("projection_matrix", 3, 4, P),
    ]
    if mounting is not None:
        T = mounting.T_vehicle_from_cam if isinstance(mounting, CameraMounting) else mounting
        T = np.asarray(T, dtype=np.float64)
        if T.shape != (4, 4) or not all(math.isfinite(v) for v in T.ravel()):
            raise InvalidInputError("T_vehicle_from_cam must be a finite 4x4 matrix")
        lines += ["# where the camera sits: vehicle frame x forward, y left, z up; camera OpenCV"]
        lines += _matrix("T_vehicle_from_cam", 4, 4, T.ravel())
    path = Path(path)
    path.write_text("\n".join(lines) + "\n")
    return path
