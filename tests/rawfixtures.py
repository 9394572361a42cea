"""Small raw recording folders made by the tests themselves (independent of the simulator)."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np

from vfdata.calibration import StereoCalibration

T0_NS = 1_700_000_000_000_000_000
FRAME_NS = 33_333_333


def calibration(width: int = 160, height: int = 128, rectified: bool = True) -> StereoCalibration:
    K = np.array([[200.0, 0, width / 2], [0, 200.0, height / 2], [0, 0, 1]])
    if rectified:
        return StereoCalibration(width, height, K, np.zeros(5), K.copy(), np.zeros(5), np.eye(3),
                                 np.array([-4.5, 0.0, 0.0]))
    R = cv2.Rodrigues(np.array([0.0, 0.01, 0.002]))[0]
    return StereoCalibration(width, height, K, np.array([-0.1, 0.01, 0, 0, 0]), K * [[1.01], [1.01], [1]],
                             np.array([-0.08, 0.0, 0, 0, 0]), R, np.array([-4.5, 0.05, 0.1]))


def frames(n: int, width: int, height: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.integers(0, 255, (height, width * 2, 3), dtype=np.uint8), (5, 5), 0)
    pairs = []
    for i in range(n):
        left = np.roll(base, i, axis=1)[:, :width].copy()
        right = np.roll(base, i + 6, axis=1)[:, :width].copy()
        pairs.append((left, right))
    return pairs


def make_raw(folder: Path, n: int = 12, width: int = 160, height: int = 128, *, video: str | None = None,
             force_rate_hz: float = 1000.0, pose: bool = True, rostopic: bool = False, seed: int = 0,
             rectified: bool = True, suffix: str = ".png") -> Path:
    """A raw folder: `video` None (image folders, `suffix` .png or .jpg), 'pair' (left.avi/right.avi) or 'sbs'
    (stereo.avi)."""
    folder.mkdir(parents=True, exist_ok=True)
    pairs = frames(n, width, height, seed)
    if video is None:
        for side in ("left", "right"):
            (folder / side).mkdir(exist_ok=True)
        for i, (left, right) in enumerate(pairs):
            cv2.imwrite(str(folder / "left" / f"{i:06d}{suffix}"), left)
            cv2.imwrite(str(folder / "right" / f"{i:06d}{suffix}"), right)
    else:
        fourcc = cv2.VideoWriter_fourcc(*"MJPG")
        if video == "pair":
            writers = [cv2.VideoWriter(str(folder / f"{side}.avi"), fourcc, 30, (width, height))
                       for side in ("left", "right")]
            for left, right in pairs:
                writers[0].write(left)
                writers[1].write(right)
        else:
            writers = [cv2.VideoWriter(str(folder / "stereo.avi"), fourcc, 30, (2 * width, height))]
            for left, right in pairs:
                writers[0].write(np.hstack([left, right]))
        for w in writers:
            w.release()
    stamps = T0_NS + np.arange(n, dtype=np.int64) * FRAME_NS
    with open(folder / "frames.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", "timestamp_ns"])
        w.writerows([i, int(t)] for i, t in enumerate(stamps))
    period = int(1e9 / force_rate_hz)
    force_t = np.arange(stamps[0] - 5 * period, stamps[-1] + 5 * period, period, dtype=np.int64)
    phase = (force_t - T0_NS) / 1e9
    wrench = np.stack([np.sin(phase * k) * k for k in range(1, 7)], axis=1)
    with open(folder / "force.csv", "w", newline="") as f:
        w = csv.writer(f)
        if rostopic:
            w.writerow(["%time", "field.header.seq", "field.header.stamp", "field.header.frame_id",
                        "field.wrench.force.x", "field.wrench.force.y", "field.wrench.force.z",
                        "field.wrench.torque.x", "field.wrench.torque.y", "field.wrench.torque.z"])
            for k, (t, row) in enumerate(zip(force_t, wrench, strict=True)):
                w.writerow([int(t) + 3_000_000, k, int(t), "ati_sensor", *[repr(float(v)) for v in row]])
        else:
            w.writerow(["timestamp_ns", "fx", "fy", "fz", "tx", "ty", "tz"])
            for t, row in zip(force_t, wrench, strict=True):
                w.writerow([int(t), *[repr(float(v)) for v in row]])
    if pose:
        with open(folder / "ecm_pose.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["timestamp_ns", "x", "y", "z", "qx", "qy", "qz", "qw"])
            for i, t in enumerate(stamps):
                angle = 0.01 * i
                w.writerow([int(t), 0.1, 0.2 + 0.001 * i, 0.3, np.sin(angle / 2), 0.0, 0.0, np.cos(angle / 2)])
    calibration(width, height, rectified).save(folder / "calibration.yaml")
    (folder / "meta.yaml").write_text("study: test\ntissue: glove\norientation_deg: 90\nsplit: test\n")
    return folder
