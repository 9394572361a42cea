"""The stereo frames of a raw recording folder: left/ and right/ image folders, two videos, or one
side-by-side video (docs/raw_layout.md); and the size of a colour JPEG read from its header."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2

from vfdata.errors import InputError
from vfdata.video_log import quiet_ffmpeg_log

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm")


class StereoSource:
    """Yields (left, right) BGR frames with a name for error messages, from folders or videos."""

    def __init__(self, folder: Path):
        self.folder = folder
        left_dir, right_dir = folder / "left", folder / "right"
        self.kind = None
        if left_dir.is_dir() or right_dir.is_dir():
            for d in (left_dir, right_dir):
                if not d.is_dir():
                    raise InputError(d, "folder not found (left/ and right/ must both exist)")
            self.left_files = sorted(p for p in left_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            self.right_files = sorted(p for p in right_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not self.left_files:
                raise InputError(left_dir, "no image files")
            if len(self.left_files) != len(self.right_files):
                raise InputError(
                    right_dir, f"{len(self.right_files)} frames but left/ has {len(self.left_files)}"
                )
            self.kind = "folders"
            self.count = len(self.left_files)
            return
        left_video = _find_video(folder, "left")
        right_video = _find_video(folder, "right")
        stereo_video = _find_video(folder, "stereo")
        if left_video or right_video:
            for name, video in (("left", left_video), ("right", right_video)):
                if video is None:
                    raise InputError(folder / f"{name}.mp4", "video not found (left and right videos must both exist)")
            self.kind = "videos"
            self.left_video, self.right_video = left_video, right_video
            left_n, right_n = _video_frame_count(left_video), _video_frame_count(right_video)
            if left_n != right_n:
                raise InputError(right_video, f"{right_n} frames but {left_video.name} has {left_n}")
            self.count = left_n
            return
        if stereo_video:
            self.kind = "side_by_side"
            self.stereo_video = stereo_video
            self.count = _video_frame_count(stereo_video)
            return
        raise InputError(folder, "no images: expected left/ and right/ folders, left.mp4 and right.mp4, or stereo.mp4")

    def __iter__(self) -> Iterator[tuple[str, object, object]]:
        """(name, left, right): for folders the items are file paths (decoded by the workers), for
        videos decoded arrays."""
        if self.kind == "folders":
            for left, right in zip(self.left_files, self.right_files, strict=True):
                yield f"{left.parent.name}/{left.name}", left, right
        elif self.kind == "videos":
            yield from _iter_video_pair(self.left_video, self.right_video)
        else:
            yield from _iter_side_by_side(self.stereo_video)


def _find_video(folder: Path, stem: str) -> Path | None:
    for suffix in VIDEO_SUFFIXES:
        path = folder / f"{stem}{suffix}"
        if path.is_file():
            return path
    return None


def _open_video(path: Path) -> cv2.VideoCapture:
    quiet_ffmpeg_log()  # our line names the file; FFmpeg's own would come first
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise InputError(path, "video cannot be opened")
    return capture


def _video_frame_count(path: Path) -> int:
    capture = _open_video(path)
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    capture.release()
    return count


def _iter_video_pair(left_path: Path, right_path: Path):
    left, right = _open_video(left_path), _open_video(right_path)
    try:
        i = 0
        while True:
            ok_l, frame_l = left.read()
            ok_r, frame_r = right.read()
            if not ok_l and not ok_r:
                return
            if ok_l != ok_r:
                short = right_path if ok_l else left_path
                raise InputError(short, f"ends at frame {i} before the other video")
            yield f"frame {i}", frame_l, frame_r
            i += 1
    finally:
        left.release()
        right.release()


def _iter_side_by_side(path: Path):
    capture = _open_video(path)
    try:
        i = 0
        while True:
            ok, frame = capture.read()
            if not ok:
                return
            if frame.shape[1] % 2:
                raise InputError(path, f"frame {i}: side-by-side width {frame.shape[1]} is odd")
            half = frame.shape[1] // 2
            yield f"frame {i}", frame[:, :half], frame[:, half:]
            i += 1
    finally:
        capture.release()


def jpeg_colour_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from the frame header of a 3-component (colour) baseline or progressive JPEG;
    None for anything else (grayscale, CMYK, not a JPEG, no frame header)."""
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        length = int.from_bytes(data[i + 2:i + 4], "big")
        # SOF0-SOF15 except DHT (C4), JPG (C8) and DAC (CC) carry the frame size.
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 10 > len(data):
                return None
            height = int.from_bytes(data[i + 5:i + 7], "big")
            width = int.from_bytes(data[i + 7:i + 9], "big")
            return (width, height) if data[i + 9] == 3 else None
        if marker == 0xDA:  # start of scan before any frame header
            return None
        i += 2 + length
    return None
