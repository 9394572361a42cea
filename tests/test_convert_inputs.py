"""Raw-folder inputs the converter must store faithfully or refuse with one line (docs/raw_layout.md):
the tables, calibration.yaml, meta.yaml; and the order of what it writes."""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from convert_fixtures import out_of_order_chunks
from rawfixtures import T0_NS, make_raw

from vfdata.cli import main
from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder, read_force_csv
from vfdata.errors import InputError
from vfdata.force_coverage import check_force_covers, default_force_gap_ns
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


GAO = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "gao2018" / "1-1-force.csv"


def write_frames(folder: Path, stamps_ns) -> None:
    with open(folder / "frames.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", "timestamp_ns"])
        w.writerows([i, int(t)] for i, t in enumerate(stamps_ns))


@pytest.mark.skipif(not GAO.exists(), reason="../shared not present")
def test_real_30hz_force_log_with_a_dropped_sample_converts(tmp_path, capsys):
    """gao2018's OptoForce log: 30 Hz, one 70 ms gap (a dropped sample) after row 132. The default
    tolerance is relative to the stream's rate (3 x 30 ms), so it converts; 50 ms given explicitly
    refuses it with a message naming the option."""
    stamps, _, _ = read_force_csv(GAO)
    src = make_raw(tmp_path / "rec", n=31)
    shutil.copyfile(GAO, src / "force.csv")
    write_frames(src, stamps[120:151])  # frame i at force row 120 + i, as the dataset's frames are
    (src / "ecm_pose.csv").unlink()
    out = convert_raw_folder(src, tmp_path / "rec.mcap", options=QUIET)
    assert np.array_equal(Recording.open(out).force.times_ns, stamps)
    assert main(["convert", "--quiet", "--force-gap-ms", "50", str(src), str(tmp_path / "b.mcap")]) == 1
    err = capsys.readouterr().err
    assert "gap of 69.9 ms in the force stream" in err and "--force-gap-ms" in err


def test_force_gap_default_is_relative_to_the_rate():
    assert default_force_gap_ns(np.arange(0, 10**9, 1_000_000)) == 50_000_000  # 1 kHz: the 50 ms floor
    assert default_force_gap_ns(np.arange(0, 10**10, 30_000_000)) == 90_000_000  # 30 Hz: 3 periods
    stalled = np.concatenate([np.arange(0, 10**8, 1_000_000), [10**8 + 60_000_000]])
    with pytest.raises(InputError, match=r"gap of 61\.0 ms .*default tolerance 50 ms.*--force-gap-ms"):
        check_force_covers(Path("force.csv"), stalled, np.array([0, 10**8 + 60_000_000]))


def _broken_videos(src: Path) -> None:
    """A real left/right MP4 pair cut in half (the index, FFmpeg's 'moov atom', is never written)."""
    for side in ("left", "right"):
        shutil.rmtree(src / side)
        writer = cv2.VideoWriter(str(src / f"{side}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30, (160, 128))
        for frame in np.random.default_rng(0).integers(0, 256, (12, 128, 160, 3), np.uint8):
            writer.write(frame)
        writer.release()
        data = (src / f"{side}.mp4").read_bytes()
        (src / f"{side}.mp4").write_bytes(data[:len(data) // 2])


def _text_video(src: Path) -> None:
    shutil.rmtree(src / "left")
    shutil.rmtree(src / "right")
    (src / "stereo.mp4").write_text("not a video, a note someone saved under the video's name\n")


@pytest.mark.parametrize("make, bad", [(_broken_videos, "left.mp4"), (_text_video, "stereo.mp4")])
def test_a_video_that_does_not_open_is_our_one_line_without_ffmpegs(tmp_path, make, bad):
    """In a process of its own: OpenCV sets FFmpeg's log level when it first opens a video."""
    src = make_raw(tmp_path / "rec", n=12)
    make(src)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    env.pop("OPENCV_FFMPEG_LOGLEVEL", None)
    done = subprocess.run([sys.executable, "-m", "vfdata", "convert", "--quiet", str(src), str(tmp_path / "o.mcap")],
                          capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [f"vfdata convert: error: {src / bad}: video cannot be opened"]
    assert not (tmp_path / "o.mcap").exists()
