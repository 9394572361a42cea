"""The tables of a raw recording folder (docs/raw_layout.md): frames.csv, force.csv (ours or a
`rostopic echo -p` export), ecm_pose.csv -> stamps (int ns) and values, checked row by row; any
problem is an InputError naming the file and the line.

Strict where a lenient reader would store wrong values: UTF-8 text only (a BOM is fine), every row
with as many fields as the header (an unquoted decimal comma, `0,011748`, splits a value in two),
numbers in ASCII digits only (Python's int() and float() also take other scripts' digits and `1_000`),
stamps within ROS time (0 to 2**31 s)."""

from __future__ import annotations

import csv
import io
import re
from pathlib import Path

import numpy as np

from vfdata.errors import InputError
from vfdata.recording import layout
from vfdata.recording.messages import MAX_STAMP_NS

ROSTOPIC_WRENCH_COLUMNS = [
    "field.header.stamp", "field.wrench.force.x", "field.wrench.force.y", "field.wrench.force.z",
    "field.wrench.torque.x", "field.wrench.torque.y", "field.wrench.torque.z",
]
_INTEGER = re.compile(r"\s*[+-]?[0-9]+\s*", re.ASCII)
_NUMBER = re.compile(r"\s*[+-]?(([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?|nan|inf|infinity)\s*",
                     re.ASCII | re.IGNORECASE)


def read_frames_csv(path: Path) -> np.ndarray:
    """frames.csv (`frame,timestamp_ns`) -> (N,) int64 stamps, strictly increasing."""
    table = _read_table(path).require(["frame", "timestamp_ns"])
    stamps = table.stamps("timestamp_ns")
    frames = table.integers("frame")
    if len(stamps) == 0:
        raise InputError(path, "no rows")
    if not np.array_equal(frames, np.arange(len(frames))):
        bad = int(np.nonzero(frames != np.arange(len(frames)))[0][0])
        raise InputError(path, f"line {table.lines[bad]}: frame numbers must run 0, 1, 2, ... (found {frames[bad]})")
    table.check_increasing(stamps)
    return stamps


def read_force_csv(path: Path) -> tuple[np.ndarray, np.ndarray, str]:
    """force.csv, ours (`timestamp_ns,fx,fy,fz,tx,ty,tz`) or a `rostopic echo -p` WrenchStamped export
    (acquisition time = field.header.stamp) -> stamps (N,) int64, wrench (N, 6), frame_id."""
    table = _read_table(path)
    frame_id = layout.SENSOR_FRAME
    if "field.header.stamp" in table.header:
        table.require(ROSTOPIC_WRENCH_COLUMNS)
        stamps = table.stamps("field.header.stamp")
        wrench = table.numbers(ROSTOPIC_WRENCH_COLUMNS[1:])
        if "field.header.frame_id" in table.header:
            frame_ids = set(table.column("field.header.frame_id"))
            frame_id = frame_ids.pop() if len(frame_ids) == 1 else layout.SENSOR_FRAME
    else:
        columns = ["fx", "fy", "fz", "tx", "ty", "tz"]
        table.require(["timestamp_ns", *columns])
        stamps = table.stamps("timestamp_ns")
        wrench = table.numbers(columns)
    if len(stamps) == 0:
        raise InputError(path, "no force samples")
    table.check_finite(wrench)
    table.check_increasing(stamps)
    return stamps, wrench, frame_id or layout.SENSOR_FRAME


def read_folder_tables(src: Path) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, str],
                                             tuple[np.ndarray, np.ndarray] | None]:
    """A raw folder's frames.csv stamps, force.csv (stamps, (N, 6) wrench, frame id) and ecm_pose.csv
    (stamps, (N, 7)) when there is one."""
    frame_ns = read_frames_csv(src / "frames.csv")
    force = read_force_csv(src / "force.csv")
    pose_path = src / "ecm_pose.csv"
    return frame_ns, force, read_pose_csv(pose_path) if pose_path.exists() else None


def read_pose_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """ecm_pose.csv (`timestamp_ns,x,y,z,qx,qy,qz,qw`, metres) -> stamps, (N, 7) with unit quaternions."""
    columns = ["x", "y", "z", "qx", "qy", "qz", "qw"]
    table = _read_table(path).require(["timestamp_ns", *columns])
    stamps = table.stamps("timestamp_ns")
    values = table.numbers(columns)
    if len(stamps) == 0:
        raise InputError(path, "no poses")
    table.check_finite(values)
    table.check_increasing(stamps)
    norms = np.linalg.norm(values[:, 3:], axis=1)
    if (norms < 1e-6).any():
        raise InputError(path, f"line {table.lines[int(np.argmax(norms < 1e-6))]}: quaternion has zero length")
    values[:, 3:] /= norms[:, None]
    return stamps, values


class _Table:
    """A CSV file read as text: its header, its rows (fields as strings) and, for messages, the file
    line of each row (found again only when a message needs one: blank lines and quoted line breaks
    make it differ from the row number)."""

    def __init__(self, path: Path, text: str, header: list[str], rows: list[list[str]]):
        self.path, self._text, self.header, self.rows = path, text, header, rows
        self._lines: list[int] | None = None

    @property
    def lines(self) -> list[int]:
        if self._lines is None:
            reader = csv.reader(io.StringIO(self._text, newline=""))
            next(reader)
            self._lines = [reader.line_num for row in reader if row]
        return self._lines

    def require(self, columns: list[str]) -> _Table:
        """This table, which must have `columns`, each once."""
        missing = [c for c in columns if c not in self.header]
        if missing:
            raise InputError(self.path, f"missing column(s) {', '.join(missing)}")
        repeated = sorted({c for c in columns if self.header.count(c) > 1})
        if repeated:
            raise InputError(self.path, f"column(s) {', '.join(repeated)} appear more than once in the header")
        return self

    def column(self, name: str) -> list[str]:
        i = self.header.index(name)
        return [row[i] for row in self.rows]

    def integers(self, name: str) -> np.ndarray:
        values = self.column(name)
        try:
            parsed = [int(v) for v in values]
        except ValueError:
            parsed = None
        if parsed is None or not _plain(values):
            bad = next(k for k, v in enumerate(values) if not _INTEGER.fullmatch(v))
            raise InputError(self.path, f"line {self.lines[bad]}: {name} '{values[bad]}' is not an integer")
        if parsed and not -2**63 <= min(parsed) <= max(parsed) < 2**63:
            bad = next(k for k, v in enumerate(parsed) if not -2**63 <= v < 2**63)
            raise InputError(self.path, f"line {self.lines[bad]}: {name} {values[bad].strip()} is out of range")
        return np.array(parsed, dtype=np.int64)

    def stamps(self, name: str) -> np.ndarray:
        """A column of stamps: integer ns within ROS time (0 .. 2**31 s, the int32 seconds of its header)."""
        stamps = self.integers(name)
        bad = (stamps < 0) | (stamps > MAX_STAMP_NS)
        if bad.any():
            k = int(np.argmax(bad))
            what = "is negative" if stamps[k] < 0 else "is beyond ROS time (2**31 s after 1970, in 2038)"
            raise InputError(self.path, f"line {self.lines[k]}: {name} {stamps[k]} {what}; stamps are ns since the "
                                        "epoch or since the start of the recording")
        return stamps

    def numbers(self, names: list[str]) -> np.ndarray:
        """Columns of decimal numbers (NaN and inf read as such, for `check_finite` to name)."""
        out = np.empty((len(self.rows), len(names)), dtype=np.float64)
        for j, name in enumerate(names):
            values = self.column(name)
            try:
                out[:, j] = [float(v) for v in values]
            except ValueError:
                values_ok = False
            else:
                values_ok = _plain(values)
            if not values_ok:
                bad = next(k for k, v in enumerate(values) if not _NUMBER.fullmatch(v))
                hint = " (a decimal comma? write decimals with '.')" if "," in values[bad] else ""
                raise InputError(self.path, f"line {self.lines[bad]}: {name} '{values[bad]}' is not a number{hint}")
        return out

    def check_finite(self, values: np.ndarray) -> None:
        bad = ~np.isfinite(values).all(axis=1)
        if bad.any():
            raise InputError(self.path, f"line {self.lines[int(np.argmax(bad))]}: NaN or inf value")

    def check_increasing(self, stamps: np.ndarray) -> None:
        steps = np.diff(stamps)
        if (steps <= 0).any():
            i = int(np.argmax(steps <= 0))
            what = "repeats" if steps[i] == 0 else "goes backwards"
            raise InputError(self.path, f"line {self.lines[i + 1]}: timestamp {stamps[i + 1]} {what} "
                                        f"(previous {stamps[i]})")


def _plain(values: list[str]) -> bool:
    """Only ASCII and no digit-group underscores: what int() and float() read beyond plain numbers."""
    joined = "".join(values)
    return joined.isascii() and "_" not in joined


def _read_table(path: Path) -> _Table:
    if not path.is_file():
        raise InputError(path, "file not found")
    data = path.read_bytes()
    try:
        text = data.decode("utf-8-sig")  # a BOM (Excel's "CSV UTF-8") is not part of the first column's name
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        raise InputError(path, f"line {line}: not UTF-8 text (byte 0x{data[exc.start]:02x}); save it as UTF-8 "
                               "(or plain ASCII) CSV") from None
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        header = next(reader, None)
        if header is None:
            raise InputError(path, "file is empty")
        header = [name.strip() for name in header]
        if len(header) == 1 and ";" in header[0]:
            raise InputError(path, "fields are separated by ';': export it comma-separated, with '.' decimals")
        rows = list(reader)
    except csv.Error as exc:
        raise InputError(path, f"line {reader.line_num}: not a readable CSV line ({exc})") from None
    table = _Table(path, text, header, rows)
    if not all(rows):
        table.rows = rows = [row for row in rows if row]  # blank lines
    if set(map(len, rows)) - {len(header)}:
        bad = next(k for k, row in enumerate(rows) if len(row) != len(header))
        raise InputError(path, _field_count_problem(table.lines[bad], len(rows[bad]), len(header)))
    return table


def _field_count_problem(line: int, found: int, expected: int) -> str:
    if found > expected:
        return (f"line {line}: {found} fields but the header has {expected}: a decimal comma in a comma-separated "
                "file (0,011748)? write decimals with '.', or quote the fields")
    return f"line {line}: {found} fields but the header has {expected} (a line cut short?)"
