"""meta.yaml of a raw recording folder -> the fields of the recording's metadata record
(docs/raw_layout.md, docs/format.md). Every value is checked for what it is used as: the known keys
by type and meaning (`prompt_box` as the box `vfdata process` will use, `gravity_up_world` as a
direction), the others stored as text, or as JSON when they are not text."""

from __future__ import annotations

import datetime
import json
import math
from pathlib import Path

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


def recording_fields(meta: dict, path: Path, default_id: str, image_size: tuple[int, int]) -> dict:
    """Keyword arguments of `layout.RecordingMeta` from a meta.yaml mapping: recording_id, study,
    tissue, orientation_deg, split, gravity_up_world and `extra` (every other key). `path` names the
    file in errors; `image_size` (width, height) bounds `prompt_box`."""
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


def _kind(value) -> str:
    return {list: "a list", dict: "a mapping", bool: f"{value}", type(None): "empty"}.get(type(value), repr(value))
