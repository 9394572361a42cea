"""Parquet columns of a LeRobot dataset <-> numpy arrays, with pyarrow.

A feature of shape (1,) is a plain column; (n,) a list column (LeRobot writes `fixed_size_list`);
(a, b, ...) nested lists (the storage of the `datasets` ArrayND types); `image` a struct of encoded
`bytes` and a `path`. Reading checks every row against the feature's shape: a ragged or missing value
is an InputError naming the file and the column, never a silently reshaped array."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from vfdata.errors import InputError


def _table(path: Path, columns: list[str] | None = None, filters=None) -> pa.Table:
    if not path.is_file():
        raise InputError(path, "not found")
    try:
        return pq.read_table(path, columns=columns, filters=filters)
    except (pa.ArrowException, OSError, ValueError) as exc:
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(path, f"not a readable Parquet file of this dataset ({text})") from None


def column_names(path: Path) -> list[str]:
    try:
        return list(pq.read_schema(path).names)
    except (pa.ArrowException, OSError) as exc:
        raise InputError(path, f"not a readable Parquet file ({str(exc).splitlines()[0]})") from None


def read_records(path: Path, skip_prefix: str | None = None) -> list[dict]:
    """The rows of a (small, metadata) Parquet file as dicts, leaving out columns named `skip_prefix...`."""
    names = [n for n in column_names(path) if skip_prefix is None or not n.startswith(skip_prefix)]
    return _table(path, names).to_pylist()


def read_rows(path: Path, episode_index: int, length: int, columns: list[str]) -> dict[str, pa.Array]:
    """The `columns` of one episode's rows (in frame_index order) of a data file; each must have
    exactly `length` rows, frame_index running 0, 1, ..."""
    present = column_names(path)
    missing = [c for c in ("episode_index", "frame_index", *columns) if c not in present]
    if missing:
        raise InputError(path, f"no column {missing[0]!r} (the dataset's info.json names it)")
    wanted = list(dict.fromkeys(["frame_index", *columns]))
    table = _table(path, wanted, filters=[("episode_index", "=", episode_index)])
    if table.num_rows != length:
        raise InputError(path, f"episode {episode_index}: {table.num_rows} rows but meta/ says {length} frames")
    frames = table.column("frame_index").to_numpy()
    order = np.argsort(frames, kind="stable")
    if not np.array_equal(frames[order], np.arange(length)):
        raise InputError(path, f"episode {episode_index}: frame_index does not run 0..{length - 1}")
    return {name: table.column(name).combine_chunks().take(pa.array(order)) for name in columns}


def to_numpy(array: pa.Array, shape: tuple[int, ...], path: Path, name: str) -> np.ndarray:
    """A column as (rows, *shape): plain for shape (1,), (nested) lists of exactly `shape` otherwise."""
    rows = len(array)
    if array.null_count:
        raise InputError(path, f"column {name!r}: {array.null_count} empty value(s)")
    dims = () if shape == (1,) and not _is_list(array.type) else shape
    for depth, dim in enumerate(dims):
        if not _is_list(array.type):
            raise InputError(path, f"column {name!r} is not a list of shape {list(shape)} (level {depth}: "
                                   f"{array.type})")
        lengths = pc.list_value_length(array).to_numpy(zero_copy_only=False)
        if len(lengths) and (lengths != dim).any():
            bad = int(np.argmax(lengths != dim))
            raise InputError(path, f"column {name!r}: a value has {lengths[bad]} entries where the feature's shape "
                                   f"{list(shape)} says {dim}")
        array = array.flatten()
        if array.null_count:
            raise InputError(path, f"column {name!r}: {array.null_count} empty value(s)")
    if _is_list(array.type) or not (pa.types.is_integer(array.type) or pa.types.is_floating(array.type)
                                    or pa.types.is_boolean(array.type)):
        raise InputError(path, f"column {name!r} holds {array.type}, not numbers of shape {list(shape)}")
    return array.to_numpy(zero_copy_only=False).reshape(rows, *shape)


def _is_list(kind: pa.DataType) -> bool:
    return pa.types.is_list(kind) or pa.types.is_large_list(kind) or pa.types.is_fixed_size_list(kind)


def image_bytes(array: pa.Array, path: Path, name: str) -> list[tuple[bytes | None, str | None]]:
    """An `image` column (struct of `bytes` and `path`) as (encoded bytes, path) per row."""
    if not pa.types.is_struct(array.type) or array.type.get_field_index("bytes") < 0:
        raise InputError(path, f"column {name!r} is not an image column (struct of bytes and path)")
    data = array.field("bytes").to_pylist()
    paths = array.field("path").to_pylist() if array.type.get_field_index("path") >= 0 else [None] * len(data)
    return list(zip(data, paths, strict=True))


# -- writing ------------------------------------------------------------------------------------------
def to_arrow(values: np.ndarray, shape: tuple[int, ...]) -> pa.Array:
    """(rows, *shape) values as a column: plain for shape (1,), fixed-size lists otherwise (what
    LeRobot's own writer produces)."""
    rows = len(values)
    if shape == (1,):
        return pa.array(np.ascontiguousarray(values).reshape(rows))
    array: pa.Array = pa.array(np.ascontiguousarray(values).reshape(-1))
    for dim in reversed(shape):
        array = pa.FixedSizeListArray.from_arrays(array, dim)
    return array


def write_table(path: Path, columns: dict[str, pa.Array], metadata: dict[bytes, bytes] | None = None) -> None:
    table = pa.table(columns)
    if metadata:
        table = table.replace_schema_metadata(metadata)
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path, compression="snappy")
