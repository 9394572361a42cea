"""Raw-folder inputs the converter must store faithfully or refuse with one line (docs/raw_layout.md):
the tables, calibration.yaml, meta.yaml; and the order of what it writes."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
from convert_fixtures import out_of_order_chunks
from rawfixtures import T0_NS, make_raw

from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder
from vfdata.recording import Recording

QUIET = ConvertOptions(progress=False, image_format="png")


def write_pose(folder: Path, stamps_ns: np.ndarray) -> None:
    with open(folder / "ecm_pose.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["timestamp_ns", "x", "y", "z", "qx", "qy", "qz", "qw"])
        w.writerows([int(t), 0.1, 0.2, 0.3, 0.0, 0.0, 0.0, 1.0] for t in stamps_ns)


def test_force_and_pose_between_frames_are_merged_in_time_order(tmp_path):
    src = make_raw(tmp_path / "rec", n=30)
    pose_ns = T0_NS + 1234 + 5_000_000 * np.arange(200)  # 200 Hz, between the frames and force samples
    write_pose(src, pose_ns)
    out = convert_raw_folder(src, tmp_path / "rec.mcap", options=QUIET)
    assert out_of_order_chunks(out) == []
    assert np.array_equal(Recording.open(out).ecm_pose.times_ns, pose_ns)
