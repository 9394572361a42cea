"""The MP4 videos of a LeRobot dataset, with PyAV (FFmpeg's libraries, in its wheel).

Writing: frames at a constant rate (pts = frame number, time base 1/fps), as LeRobot writes them: AV1
(SVT-AV1) or H.264 (x264), `yuv420p`, a keyframe every `gop` frames (LeRobot's default 2: a frame
anywhere in the file decodes after at most one other). Several episodes follow one another in one
file; an episode starts at `frames_before / fps` seconds.

Reading: an episode's frames at their timestamps (the `timestamp` column, seconds from the episode's
start, plus the episode's `from_timestamp` in the file), each matched to the decoded frame within
half a frame period; a missing or undecodable frame is an InputError naming the video."""

from __future__ import annotations

import os
from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path

import numpy as np

from vfdata.errors import InputError, VisionForceError

# Codec name -> the FFmpeg encoders that write it, in order of preference.
ENCODERS = {"av1": ("libsvtav1", "libaom-av1"), "h264": ("libx264", "libopenh264", "h264")}
PIX_FMT = "yuv420p"
DEFAULT_CRF = {"av1": 20, "h264": 18}  # measured in docs/lerobot.md: near-transparent for tracking
DEFAULT_GOP = 2  # LeRobot's: random access to any frame costs at most one more decode


class VideoError(VisionForceError):
    """An encoder that this machine's FFmpeg lacks, or a frame it refuses."""


def encoder_for(codec: str) -> str:
    """The first FFmpeg encoder of `codec` that PyAV's build has."""
    import av  # PyAV only where videos are written or read: the rest of vfdata starts without it

    if codec not in ENCODERS:
        raise VideoError(f"video codec {codec!r}: choose one of {', '.join(ENCODERS)}")
    for name in ENCODERS[codec]:
        if name in av.codecs_available:
            return name
    raise VideoError(f"no {codec} encoder in this PyAV build (looked for {', '.join(ENCODERS[codec])}): "
                     f"try --codec {'h264' if codec == 'av1' else 'av1'}")


class Mp4Writer:
    """One MP4 of one camera: frames appended in order (BGR uint8), at `fps` frames per second."""

    def __init__(self, path: Path, fps: int, width: int, height: int, codec: str = "av1", crf: int | None = None,
                 gop: int = DEFAULT_GOP):
        import av  # PyAV: the `lerobot` extra, imported where a video is opened

        if width % 2 or height % 2:
            raise VideoError(f"{path.name}: {width}x{height} images cannot be stored as {PIX_FMT} video (width and "
                             "height must be even)")
        name = encoder_for(codec)
        crf = DEFAULT_CRF[codec] if crf is None else crf
        options = {"crf": str(crf), "g": str(gop)}
        if name == "libsvtav1":
            options["preset"] = "8"  # measured: 3x faster than 4 at 0.1 dB less (docs/lerobot.md)
            os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its banner to stderr unless told
        elif name == "libx264":
            options["preset"] = "fast"
        self.path, self.fps, self.frames, self.bytes = path, fps, 0, 0
        self.container = av.open(str(path), "w", options={"movflags": "faststart"})
        self.stream = self.container.add_stream(name, rate=fps, options=options)
        self.stream.width, self.stream.height, self.stream.pix_fmt = width, height, PIX_FMT
        self.stream.codec_context.time_base = Fraction(1, fps)
        self.codec = codec

    def write(self, bgr: np.ndarray) -> None:
        import av  # PyAV: the `lerobot` extra, imported where a video is opened

        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(bgr), format="bgr24")
        frame.pts, frame.time_base = self.frames, Fraction(1, self.fps)
        self._mux(self.stream.encode(frame))
        self.frames += 1

    @property
    def seconds(self) -> float:
        """Where the next frame goes, in seconds from the start of the file."""
        return self.frames / self.fps

    def close(self) -> None:
        self._mux(self.stream.encode(None))
        self.container.close()

    def _mux(self, packets) -> None:
        for packet in packets:
            self.bytes += packet.size
            self.container.mux(packet)


def read_frames(path: Path, start_s: float, times_s: np.ndarray, what: str) -> Iterator[np.ndarray]:
    """The frames of `path` at `start_s + times_s` (seconds, increasing) as BGR uint8, in order; each
    must be within half a frame period of a decoded frame. `what` names the frames in errors
    ("episode 3")."""
    import av  # PyAV: the `lerobot` extra, imported where a video is opened

    if not path.is_file():
        raise InputError(path, "video not found")
    wanted = start_s + np.asarray(times_s, dtype=np.float64)
    if len(wanted) == 0:
        return
    step = float(np.median(np.diff(wanted))) if len(wanted) > 1 else 1.0
    tolerance = 0.5 * step
    j = 0
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise InputError(path, "has no video stream")
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            if wanted[0] > tolerance:
                # Seek to the keyframe at or before the episode's first frame (LeRobot's files hold many).
                container.seek(max(0, int((wanted[0] - tolerance) / stream.time_base)), stream=stream, backward=True)
            for frame in container.decode(stream):
                if frame.pts is None:
                    continue
                t = float(frame.pts * stream.time_base)
                if t > wanted[j] + tolerance:
                    raise InputError(path, f"{what}: no frame at {wanted[j]:.4f} s (the next decoded frame is at "
                                           f"{t:.4f} s)")
                if abs(t - wanted[j]) <= tolerance:
                    yield frame.to_ndarray(format="bgr24")
                    j += 1
                    if j == len(wanted):
                        return
    except av.FFmpegError as exc:
        raise InputError(path, f"{what}: cannot be decoded ({exc.strerror or exc})") from None
    raise InputError(path, f"{what}: the video ends before frame {j} of {len(wanted)} (at {wanted[j]:.4f} s)")


def psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio of two uint8 images, dB (inf when equal)."""
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse)
