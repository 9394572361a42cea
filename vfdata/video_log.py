"""FFmpeg's own log off: OpenCV's video backend lets FFmpeg print its errors to stderr (`[mov,mp4,m4a,3gp,3g2,mj2
@ 0x...] moov atom not found`) before our one line names the file and says the same. Setting
OPENCV_FFMPEG_LOGLEVEL yourself (e.g. 24, FFmpeg's warnings) shows them again."""

from __future__ import annotations

import os

AV_LOG_QUIET = -8  # FFmpeg's level that prints nothing


def quiet_ffmpeg_log() -> None:
    """Call before opening a video: OpenCV reads the level once, when its FFmpeg backend first starts in
    the process (a capture opened earlier by other code keeps FFmpeg's default, errors shown)."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", str(AV_LOG_QUIET))
