"""The converters' one write loop: a recording MCAP (layout v1) from stereo frames encoded on a thread
pool, written in frame order with the camera infos of each frame and the force and pose series
interleaved by stamp. The raw-folder and the bag converters differ only in where the frames, the
series and the camera model come from."""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np
from tqdm import tqdm

from vfdata.atomic import output_os_error
from vfdata.calibration import StereoCalibration
from vfdata.conversion.options import ConvertOptions
from vfdata.conversion.ordered_map import ordered_map
from vfdata.recording import layout
from vfdata.recording.messages import (
    NS_PER_S,
    CameraInfo,
    CompressedImage,
    PoseStamped,
    TFMessage,
    TransformStamped,
    WrenchStamped,
    encode_stamped_batch,
    encode_tf_batch,
)
from vfdata.recording.writer import IMAGE_LEVEL, McapWriter

T = TypeVar("T")
_STAMP = struct.Struct("<iI")  # header.stamp in CDR: int32 sec, uint32 nanosec
_U32 = struct.Struct("<I")
SERIES_BATCH = 512  # force and pose samples encoded and written at a time
_SHORT_RUN = 8  # runs of fewer samples of one series are written message by message (measured best)


@dataclass(frozen=True)
class StampedSeries:
    """A force or pose series to write: sorted stamps (N,) int ns, values (N, 6) wrench (N, N*m) or
    (N, 7) pose (m, quaternion xyzw), one frame id."""

    topic: str
    msgtype: str
    stamps_ns: np.ndarray
    values: np.ndarray
    frame_id: str
    child_frame_id: str | None = None  # a TFMessage series (/tf): the transform's child frame


def sensor_series(force: tuple[np.ndarray, np.ndarray, str], pose: tuple[np.ndarray, np.ndarray] | None
                  ) -> list[StampedSeries]:
    """The force series (stamps, wrench, frame id) and the ECM pose series (stamps, pose) if any."""
    series = [StampedSeries(layout.WRENCH, WrenchStamped.msgtype, *force)]
    if pose is not None:
        series.append(StampedSeries(layout.ECM_POSE, PoseStamped.msgtype, *pose, layout.WORLD_FRAME))
    return series


# -- the camera model ---------------------------------------------------------------------------------
def camera_infos(calib: StereoCalibration, stamp_ns: int) -> tuple[CameraInfo, CameraInfo]:
    """ROS CameraInfo of both views: raw K and D, rectifying R, rectified P (right P[0,3] = -fx*B, m)."""
    rect = calib.rectified
    p2 = rect.P2.copy()
    p2[0, 3] *= 1e-3  # ROS: metres
    infos = []
    for frame, K, D, R, P in (
        (layout.LEFT_FRAME, calib.K1, calib.D1, rect.R1, rect.P1),
        (layout.RIGHT_FRAME, calib.K2, calib.D2, rect.R2, p2),
    ):
        # ROS names two models: plumb_bob (k1 k2 p1 p2 k3) and rational_polynomial (k1 ... k6, and the
        # thin-prism and tilt terms after them, in OpenCV's order, as image_geometry passes D to OpenCV).
        model = "plumb_bob" if len(D) <= 5 else "rational_polynomial"
        d = np.concatenate([D, np.zeros(max(0, 5 - len(D)))])
        infos.append(CameraInfo(stamp_ns, frame, calib.height, calib.width, model, d, K, R, P))
    return infos[0], infos[1]


def stereo_tf(calib: StereoCalibration, stamp_ns: int) -> TFMessage:
    """left -> right optical frame of the rectified pair: the right camera sits `baseline` along +x."""
    baseline_m = calib.rectified.baseline_mm * 1e-3
    return TFMessage([
        TransformStamped(stamp_ns, layout.LEFT_FRAME, layout.RIGHT_FRAME, (baseline_m, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    ])


# -- payloads -----------------------------------------------------------------------------------------
def restamped(payload: bytes, stamp_ns: int) -> bytes:
    """A CDR payload of a message that starts with a std_msgs/Header, with header.stamp set to
    `stamp_ns` (sec and nanosec are bytes 4..12, after the encapsulation header)."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return payload[:4] + _STAMP.pack(sec, nanosec) + payload[12:]


def compressed_image_payload(stamp_ns: int, frame_id: str, fmt: str, data: bytes | np.ndarray) -> bytes:
    """`CompressedImage(stamp_ns, frame_id, fmt, data).encode()`, with one copy of `data` instead of three."""
    head = CompressedImage(stamp_ns, frame_id, fmt, b"").encode()[:-4]  # ends with the data length, 0
    return b"".join((head, _U32.pack(len(data)), memoryview(data).cast("B")))


def encode_image(image: np.ndarray, options: ConvertOptions) -> np.ndarray | None:
    """BGR pixels -> the encoded image of `options.image_format` (JPEG at its quality, or PNG at the
    fast compression level 1); None when OpenCV cannot encode it."""
    if options.image_format == "jpeg":
        ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, options.jpeg_quality])
    else:
        ok, data = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    return data if ok else None


# -- the write loop -----------------------------------------------------------------------------------
class _SeriesWriter:
    """Writes the force and pose series as the frames go by, merged into one stamp order: they share
    the file's series chunks (`McapWriter(separate_topics=...)`), and each chunk must hold its
    messages in log-time order (readers that stream a chunk, and `mcap doctor`, expect it).
    `write_until(stamp)` makes sure every sample up to `stamp` is written. At 1 kHz the per-call
    costs add up, so samples are encoded and written once `batch` of them are due (the series chunks
    are apart from the images, so waiting a few frames moves nothing in the file)."""

    def __init__(self, writer: McapWriter, series: list[StampedSeries], batch: int):
        self.writer, self.series, self.batch = writer, series, batch
        self.done = [0] * len(series)

    def write_until(self, stamp_ns: int | None) -> None:
        """The samples up to `stamp_ns` once `batch` of them are due; every remaining one for None."""
        stops = [len(s.stamps_ns) if stamp_ns is None else int(np.searchsorted(s.stamps_ns, stamp_ns, side="right"))
                 for s in self.series]
        if sum(stops) - sum(self.done) < (1 if stamp_ns is None else self.batch):
            return
        # Merged order of the due samples: a stable sort of the series' sorted stamps, so equal
        # stamps keep the series' order (force before pose).
        which = np.concatenate([np.full(stop - done, i) for i, (done, stop) in enumerate(zip(self.done, stops,
                                                                                              strict=True))])
        stamps = np.concatenate([s.stamps_ns[done:stop] for s, done, stop in zip(self.series, self.done, stops,
                                                                                  strict=True)])
        which = which[np.argsort(stamps, kind="stable")]
        for start in range(0, len(which), 8 * self.batch):  # a bounded table even for a long gap
            self._write_merged(which[start:start + 8 * self.batch])

    def _write_merged(self, which: np.ndarray) -> None:
        """The next len(which) samples, `which[j]` naming the series of the j-th: each series' rows
        encoded at once, then written run by run (a run: consecutive samples of one series)."""
        counts = np.bincount(which, minlength=len(self.series))
        tables = []
        for i, s in enumerate(self.series):
            rows = slice(self.done[i], self.done[i] + int(counts[i]))
            encoded = (encode_tf_batch(s.stamps_ns[rows], s.frame_id, s.child_frame_id, s.values[rows])
                       if s.child_frame_id else encode_stamped_batch(s.stamps_ns[rows], s.frame_id, s.values[rows]))
            tables.append((s.stamps_ns[rows], encoded))
        used = [0] * len(self.series)
        bounds = [0, *(np.flatnonzero(np.diff(which)) + 1).tolist(), len(which)]
        for start, stop in zip(bounds[:-1], bounds[1:], strict=True):
            i, n = int(which[start]), stop - start
            stamps, table = tables[i]
            s = self.series[i]
            rows = slice(used[i], used[i] + n)
            if n < _SHORT_RUN:  # one call per message costs less than a bulk call for a few
                for stamp, row in zip(stamps[rows].tolist(), table[rows], strict=True):
                    self.writer.write_payload(s.topic, s.msgtype, stamp, row.tobytes())
            else:
                self.writer.write_payloads(s.topic, s.msgtype, stamps[rows], table[rows])
            used[i] += n
        for i, n in enumerate(used):
            self.done[i] += n


@dataclass(frozen=True)
class View:
    """One camera view of a recording: its image topic and message type, and its CameraInfo topic."""

    image_topic: str
    image_msgtype: str
    info_topic: str


STEREO_VIEWS = (View(layout.LEFT_IMAGE, CompressedImage.msgtype, layout.LEFT_INFO),
                View(layout.RIGHT_IMAGE, CompressedImage.msgtype, layout.RIGHT_INFO))


def write_recording(out: Path, overwrite: bool, options: ConvertOptions, record: layout.RecordingMeta,
                    infos: tuple[CameraInfo, ...], tf: TFMessage, frame_ns: np.ndarray,
                    frames: Iterable[T], encode: Callable[[T], tuple[bytes, ...]],
                    series: list[StampedSeries], name: str, views: tuple[View, ...] = STEREO_VIEWS) -> None:
    """Write the recording to `out` (atomically: nothing is left on any error).

    `frames` yields one item per frame, in frame order; `encode(item)` (called on the encoding
    threads) turns item k into the image payloads of its views (default: the left and right
    CompressedImage), stamped `frame_ns[k]`. The camera infos (one per view, restamped each frame)
    and the transform (stamped with the first frame) come from the camera model. `name` labels the
    progress bar."""
    first = int(frame_ns[0])
    if options.time_offset_ns:  # the recording says that its sensors were moved onto the video's clock
        record = replace(record, extra={**record.extra, "sensor_time_offset_ns": str(options.time_offset_ns)})
    # The ECM pose also on /tf (world -> ecm), as ROS tools expect a moving frame.
    series = [*series, *(StampedSeries(layout.TF, TFMessage.msgtype, s.stamps_ns, s.values, s.frame_id,
                                       layout.ECM_FRAME) for s in series if s.topic == layout.ECM_POSE)]
    for transform in tf.transforms:
        transform.stamp_ns = first
    # The camera infos differ from frame to frame only by their stamp: encoded once, restamped.
    info_payloads = tuple((view.info_topic, info.encode()) for view, info in zip(views, infos, strict=True))
    workers = max(1, options.workers)
    try:
        with McapWriter(out, overwrite=overwrite, chunk_size=options.chunk_size,
                        separate_topics=(layout.WRENCH, layout.ECM_POSE, layout.TF),
                        chunk_level=IMAGE_LEVEL) as writer, \
                ThreadPoolExecutor(workers) as pool:
            writer.add_metadata(layout.RECORDING_METADATA, record.to_record())
            writer.write(layout.TF_STATIC, tf)
            # Samples up to each frame's stamp are written before it, so the file is in time order.
            series_writer = _SeriesWriter(writer, series, SERIES_BATCH)
            encoded = ordered_map(pool, encode, frames, window=4 * workers)
            with tqdm(total=len(frame_ns), desc=f"convert {name}", unit="frame", disable=not options.progress) as bar:
                for k, payloads in enumerate(encoded):
                    stamp = int(frame_ns[k])
                    series_writer.write_until(stamp)
                    for topic, payload in info_payloads:
                        writer.write_payload(topic, CameraInfo.msgtype, stamp, restamped(payload, stamp))
                    for view, payload in zip(views, payloads, strict=True):
                        writer.write_payload(view.image_topic, view.image_msgtype, stamp, payload)
                    bar.update()
            series_writer.write_until(None)
    except OSError as exc:  # the writer's own file operations carry no name, or the temporary's
        named = output_os_error(out, exc)
        if named is None:
            raise
        raise named from exc
