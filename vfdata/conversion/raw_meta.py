"""meta.yaml of a raw recording folder -> the recording's metadata record (docs/raw_layout.md,
docs/format.md)."""

from __future__ import annotations

from pathlib import Path

import yaml

from vfdata.errors import InputError


def read_meta(path: Path) -> dict:
    if not path.is_file():
        return {}
    try:
        meta = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise InputError(path, f"not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(meta, dict):
        raise InputError(path, "must be a mapping of keys to values")
    return meta


def _meta_text(value) -> str:
    return value if isinstance(value, str) else yaml.safe_dump(value, default_flow_style=True).strip()
