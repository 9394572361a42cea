"""The tables of a raw recording folder (docs/raw_layout.md): frames.csv, force.csv (ours or a
`rostopic echo -p` export), ecm_pose.csv -> stamps (int ns) and values, checked row by row; any
problem is an InputError naming the file and the line."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from vfdata.errors import InputError
from vfdata.recording import layout

ROSTOPIC_WRENCH_COLUMNS = [
    "field.header.stamp", "field.wrench.force.x", "field.wrench.force.y", "field.wrench.force.z",
    "field.wrench.torque.x", "field.wrench.torque.y", "field.wrench.torque.z",
]


def read_frames_csv(path: Path) -> np.ndarray:
    """frames.csv (`frame,timestamp_ns`) -> (N,) int64 stamps, strictly increasing."""
    rows = _read_csv(path, ["frame", "timestamp_ns"])
    stamps = _int_column(path, rows, "timestamp_ns")
    frames = _int_column(path, rows, "frame")
    if len(stamps) == 0:
        raise InputError(path, "no rows")
    if not np.array_equal(frames, np.arange(len(frames))):
        bad = int(np.nonzero(frames != np.arange(len(frames)))[0][0])
        raise InputError(path, f"line {bad + 2}: frame numbers must run 0, 1, 2, ... (found {frames[bad]})")
    _check_increasing(path, stamps)
    return stamps


def read_force_csv(path: Path) -> tuple[np.ndarray, np.ndarray, str]:
    """force.csv, ours (`timestamp_ns,fx,fy,fz,tx,ty,tz`) or a `rostopic echo -p` WrenchStamped export
    (acquisition time = field.header.stamp) -> stamps (N,) int64, wrench (N, 6), frame_id."""
    with open(path, newline="") as handle:
        header = next(csv.reader(handle), None)
    if header is None:
        raise InputError(path, "file is empty")
    if "field.header.stamp" in header:
        rows = _read_csv(path, ROSTOPIC_WRENCH_COLUMNS)
        stamps = _int_column(path, rows, "field.header.stamp")
        wrench = _float_columns(path, rows, ROSTOPIC_WRENCH_COLUMNS[1:])
        frame_ids = {r.get("field.header.frame_id", "") for r in rows}
        frame_id = frame_ids.pop() if len(frame_ids) == 1 else layout.SENSOR_FRAME
    else:
        columns = ["fx", "fy", "fz", "tx", "ty", "tz"]
        rows = _read_csv(path, ["timestamp_ns", *columns])
        stamps = _int_column(path, rows, "timestamp_ns")
        wrench = _float_columns(path, rows, columns)
        frame_id = layout.SENSOR_FRAME
    if len(stamps) == 0:
        raise InputError(path, "no force samples")
    _check_finite(path, wrench)
    _check_increasing(path, stamps)
    return stamps, wrench, frame_id or layout.SENSOR_FRAME


def read_pose_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """ecm_pose.csv (`timestamp_ns,x,y,z,qx,qy,qz,qw`, metres) -> stamps, (N, 7) with unit quaternions."""
    columns = ["x", "y", "z", "qx", "qy", "qz", "qw"]
    rows = _read_csv(path, ["timestamp_ns", *columns])
    stamps = _int_column(path, rows, "timestamp_ns")
    values = _float_columns(path, rows, columns)
    if len(stamps) == 0:
        raise InputError(path, "no poses")
    _check_finite(path, values)
    _check_increasing(path, stamps)
    norms = np.linalg.norm(values[:, 3:], axis=1)
    if (norms < 1e-6).any():
        raise InputError(path, f"line {int(np.argmax(norms < 1e-6)) + 2}: quaternion has zero length")
    values[:, 3:] /= norms[:, None]
    return stamps, values


def _read_csv(path: Path, required: list[str]) -> list[dict[str, str]]:
    if not path.is_file():
        raise InputError(path, "file not found")
    with open(path, newline="") as handle:
        reader = csv.DictReader(handle)
        missing = [c for c in required if c not in (reader.fieldnames or [])]
        if missing:
            raise InputError(path, f"missing column(s) {', '.join(missing)}")
        return list(reader)


def _int_column(path: Path, rows: list[dict[str, str]], column: str) -> np.ndarray:
    try:
        return np.array([int(r[column]) for r in rows], dtype=np.int64)
    except (TypeError, ValueError):
        bad = next(i for i, r in enumerate(rows) if not str(r[column]).strip().lstrip("-").isdigit())
        raise InputError(path, f"line {bad + 2}: {column} '{rows[bad][column]}' is not an integer") from None


def _float_columns(path: Path, rows: list[dict[str, str]], columns: list[str]) -> np.ndarray:
    try:
        return np.array([[float(r[c]) for c in columns] for r in rows], dtype=np.float64).reshape(-1, len(columns))
    except (TypeError, ValueError):
        for i, r in enumerate(rows):
            for c in columns:
                try:
                    float(r[c])
                except (TypeError, ValueError):
                    raise InputError(path, f"line {i + 2}: {c} '{r[c]}' is not a number") from None
        raise


def _check_finite(path: Path, values: np.ndarray) -> None:
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        raise InputError(path, f"line {int(np.argmax(bad)) + 2}: NaN or inf value")


def _check_increasing(path: Path, stamps: np.ndarray) -> None:
    steps = np.diff(stamps)
    if (steps <= 0).any():
        i = int(np.argmax(steps <= 0))
        what = "repeats" if steps[i] == 0 else "goes backwards"
        raise InputError(path, f"line {i + 3}: timestamp {stamps[i + 1]} {what} (previous {stamps[i]})")
