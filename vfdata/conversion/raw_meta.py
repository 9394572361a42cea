"""meta.yaml of a raw recording folder -> the fields of the recording's metadata record
(docs/raw_layout.md, docs/format.md). Every value is checked for what it is used as: the known keys
by type and meaning (`prompt_box` as the box `vfdata process` will use, `gravity_up_world` as a
direction), the others stored as text, or as JSON when they are not text."""

from __future__ import annotations

import datetime
import json
import math
from pathlib import Path

import numpy as np
import yaml

from vfdata.errors import InputError

TEXT_KEYS = ("study", "tissue", "split")
# Written by the converter itself: a meta.yaml key of one of these names is kept as meta_<name>
# (docs/raw_layout.md), not replaced.
RESERVED_KEYS = ("recording_id", "source", "converter", "converter_version", "layout_version", "units")
_JSON_BUDGET = 10_000  # values (list items, map entries) an extra key may hold


def read_meta(path: Path) -> dict:
    """The mapping in meta.yaml ({} when there is no file)."""
    if not path.is_file():
        return {}
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(path, f"not UTF-8 text (byte {exc.start}); save it as UTF-8") from None
    try:
        meta = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InputError(path, f"not valid YAML ({str(exc).splitlines()[0]})") from None
    if meta is None:
        return {}
    if not isinstance(meta, dict):
        raise InputError(path, "must be a mapping of keys to values")
    for key in meta:
        if not isinstance(key, str):
            raise InputError(path, f"key {key!r} is not text (quote it: '{key}': ...)")
    return meta


def parse_meta_pairs(items: list[str], where: str = "--meta") -> dict:
    """`KEY=VALUE` texts (vfdata convert --meta) -> a meta.yaml-like mapping; each value read as YAML, so
    numbers are numbers and [0, 0, 1] a list."""
    meta = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise InputError(where, f"'{item}' is not KEY=VALUE (e.g. orientation_deg=90, gravity_up=0,0,1)")
        if key in meta:
            raise InputError(where, f"'{key}' is given twice")
        try:
            value = yaml.safe_load(text) if text.strip() else ""
        except yaml.YAMLError:
            value = text
        meta[key] = text if isinstance(value, dict) else value  # "a: b" is text here, not a mapping
    return meta


def recording_fields(meta: dict, path: Path, default_id: str, image_size: tuple[int, int]) -> dict:
    """Keyword arguments of `layout.RecordingMeta` from a meta.yaml mapping (or `vfdata convert --meta`
    pairs, or a manifest entry's keys): recording_id, study, tissue, orientation_deg, split,
    gravity_up_world (also as `gravity_up`) and `extra` (every other key; `prompt` checked as a prompt,
    `sensor_to_object` as a rotation and stored as a 3x3 JSON matrix). `path` names the file in errors;
    `image_size` (width, height) bounds `prompt_box`."""
    meta = dict(meta)
    if "gravity_up" in meta:
        if "gravity_up_world" in meta:
            raise InputError(path, "'gravity_up' and 'gravity_up_world' are the same key: give one")
        meta["gravity_up_world"] = meta.pop("gravity_up")
    if isinstance(meta.get("gravity_up_world"), str):
        meta["gravity_up_world"] = _numbers_text(meta["gravity_up_world"])
    if "sensor_to_object" in meta:
        meta["sensor_to_object"] = sensor_to_object_matrix(meta["sensor_to_object"], path)
    if "prompt" in meta:
        _check_prompt(meta["prompt"], path)
    fields = {
        "recording_id": _text(meta, "id", path) or default_id,
        **{key: _text(meta, key, path) for key in TEXT_KEYS},
        "orientation_deg": _number(meta, "orientation_deg", path),
        "gravity_up_world": _gravity(meta, path),
    }
    extra = {}
    for key, value in meta.items():
        if key in ("id", "orientation_deg", "gravity_up_world", *TEXT_KEYS):
            continue
        if key == "prompt_box":
            _check_box(value, path, image_size)
        name = key
        if key in RESERVED_KEYS:
            name = f"meta_{key}"
            if name in meta:
                raise InputError(path, f"'{key}' is written by the converter and '{name}' is taken: rename one")
        if isinstance(value, datetime.date):  # YAML reads 2024-05-01 as a date: keep the text
            value = value.isoformat()
        extra[name] = value if isinstance(value, str) else _json_text(value, key, path)
    return {**fields, "extra": extra}


def _text(meta: dict, key: str, path: Path) -> str:
    value = meta.get(key)
    if value is None:
        return ""
    if isinstance(value, bool) or not isinstance(value, (str, int, float, datetime.date)):
        raise InputError(path, f"'{key}' must be text, not {_kind(value)}")
    return value.isoformat() if isinstance(value, datetime.date) else str(value)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _number(meta: dict, key: str, path: Path) -> float:
    value = meta.get(key)
    if value is None:
        return 0.0
    if isinstance(value, str):
        try:
            value = float(value) if value.strip().isascii() else None
        except ValueError:
            value = None
    if not _is_number(value):
        raise InputError(path, f"'{key}' must be a number (degrees), not {meta[key]!r}")
    return float(value)


def _gravity(meta: dict, path: Path) -> tuple[float, float, float]:
    value = meta.get("gravity_up_world", (0.0, 0.0, 1.0))
    if not (isinstance(value, (list, tuple)) and len(value) == 3 and all(map(_is_number, value))
            and math.hypot(*value) > 0):
        raise InputError(path, f"'gravity_up_world' must be 3 numbers [x, y, z] of non-zero length (the up "
                               f"direction in the ECM pose's world frame), not {value!r}")
    return tuple(float(v) for v in value)


def _check_box(value, path: Path, image_size: tuple[int, int]) -> None:
    """`prompt_box`: [x0, y0, x1, y1] (or the text "x0,y0,x1,y1"), pixels of the first left frame,
    x0 < x1 and y0 < y1, inside the image."""
    numbers = value
    if isinstance(value, str):
        try:
            numbers = [float(v) for v in value.split(",")] if value.isascii() else None
        except ValueError:
            numbers = None
    width, height = image_size
    if not (isinstance(numbers, (list, tuple)) and len(numbers) == 4 and all(map(_is_number, numbers))):
        raise InputError(path, f"'prompt_box' must be 4 numbers [x0, y0, x1, y1] (pixels of the first left frame), "
                               f"not {value!r}")
    x0, y0, x1, y1 = numbers
    if not (x0 < x1 and y0 < y1):
        raise InputError(path, f"'prompt_box' {list(numbers)} must have x0 < x1 and y0 < y1")
    if not (0 <= x0 and 0 <= y0 and x1 <= width and y1 <= height):
        raise InputError(path, f"'prompt_box' {list(numbers)} lies outside the {width}x{height} image")


def _json_text(value, key: str, path: Path) -> str:
    """A value that is not text as JSON (docs/format.md), dates as ISO text; refused when JSON cannot
    hold it (NaN) or it is larger than a metadata value should be (a YAML alias bomb expands)."""
    budget = [_JSON_BUDGET]

    def plain(item, depth: int = 0):
        budget[0] -= 1
        if budget[0] < 0 or depth > 32:
            raise InputError(path, f"'{key}' holds too much (more than {_JSON_BUDGET} values or 32 levels)")
        if isinstance(item, datetime.date):
            return item.isoformat()
        if isinstance(item, dict):
            return {str(k): plain(v, depth + 1) for k, v in item.items()}
        if isinstance(item, (list, tuple, set)):
            return [plain(v, depth + 1) for v in item]
        if isinstance(item, bytes):
            raise InputError(path, f"'{key}' holds binary data (!!binary), not text")
        if isinstance(item, float) and not math.isfinite(item):
            raise InputError(path, f"'{key}' holds {item}, which JSON cannot store")
        return item

    return json.dumps(plain(value))


def _numbers_text(text: str):
    """"0,0,1" -> [0.0, 0.0, 1.0]; text that is not numbers stays as it is (refused by its check)."""
    try:
        return [float(v) for v in text.strip().strip("[]").split(",")]
    except ValueError:
        return text


def sensor_to_object_matrix(value, path: Path) -> list[list[float]]:
    """The rotation from the force sensor's frame to the object frame, as a 3x3 list: given as 9 numbers
    (rows; a list, nested or flat, or text "r11,r12,...,r33") or as "xyz_deg:rx,ry,rz" (rotations about
    the fixed x, y, z axes in that order, degrees)."""
    from scipy.spatial.transform import Rotation  # scipy only for this key: conversion starts without it

    try:
        if isinstance(value, str) and value.strip().lower().startswith("xyz_deg:"):
            angles = [float(v) for v in value.split(":", 1)[1].split(",")]
            if len(angles) != 3:
                raise ValueError
            matrix = Rotation.from_euler("xyz", angles, degrees=True).as_matrix()
        else:
            numbers = _numbers_text(value) if isinstance(value, str) else value
            matrix = np.asarray(numbers, dtype=float).reshape(3, 3)
    except (ValueError, TypeError):
        raise InputError(path, f"'sensor_to_object' must be 9 numbers (a 3x3 rotation, rows) or "
                               f"xyz_deg:rx,ry,rz, not {value!r}") from None
    if not (np.isfinite(matrix).all() and np.allclose(matrix @ matrix.T, np.eye(3), atol=1e-3)
            and np.linalg.det(matrix) > 0):
        raise InputError(path, f"'sensor_to_object' {matrix.round(4).tolist()} is not a rotation (orthonormal, "
                               "determinant +1)")
    return matrix.tolist()


def _check_prompt(value, path: Path) -> None:
    from vfdata.recon.prompt import Prompt  # vfdata.recon's package loads every stage: only when a prompt is given

    if not isinstance(value, str):
        raise InputError(path, f"'prompt' must be text such as box:x0,y0,x1,y1 or points:x,y;x,y, not {value!r}")
    try:
        Prompt.parse(value)
    except InputError as exc:
        raise InputError(path, f"'prompt' {value!r}: {exc.problem}") from None


def _kind(value) -> str:
    return {list: "a list", dict: "a mapping", bool: f"{value}", type(None): "empty"}.get(type(value), repr(value))
