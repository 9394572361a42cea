"""A live session (`vfdata live`): a stereo or RGB-D source (`vfdata.sources`) through the streaming
estimator (`vfmodels.inference.live`) to a Foxglove WebSocket server (`vfdata.foxglove_server`), frame by frame.

Per tracked frame it serves the source rig's view (`vfdata.rig`: the left image,
`/stereo/left/image/compressed`, JPEG, with its rectified `/stereo/left/camera_info`; an RGB-D source:
`/camera/depth/image`, 16UC1 mm, and its camera info, in the depth camera's frame), `/tissue/mask`,
`/tissue/points` and `/tracking/points` (object frame, m), the object frame on `/tf`, and the force of
each frame on `/force/estimate` as soon as it is known (one frame later: its velocity is a central
difference; two with `pipelined`), with its band's half-width on `/force/estimate/band` and its
distance beyond the training range on `/force/estimate/beyond` (N; `vfmodels.evaluation.band`) and how unlike
training's its input is on `/force/estimate/unlike` (> 1: unlike training). The force goes
first, the pictures after it, so drawing them never delays a force.

Latency is measured from the arrival of the frame the estimate waited for (the one after the
estimate's own frame: the velocity's) to the moment its force was sent; `LiveStats` keeps them."""

from __future__ import annotations

import json
import sys
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from vfdata.engine import FrameResult
from vfdata.foxglove_server import FoxgloveServer
from vfdata.recon.object_frame import ObjectFrame, x_axis_meaning
from vfdata.recording import layout
from vfdata.recording.derived import (
    DERIVED_VERSION,
    cloud_message,
    mask_message,
    object_tf,
    wrench_of,
)
from vfdata.recording.messages import Float64
from vfdata.sources import LiveFrame
from vfmodels.inference.live import ForceEstimate, StreamingForceEstimator


@dataclass
class LiveStats:
    """What a session did: frames in, estimates out, and the timing a client sees."""

    frames: int = 0
    estimates: int = 0
    dropped: int = 0  # frames a camera delivered that the session never took (it was busy)
    wall_s: float = 0.0  # first frame's arrival to the last estimate sent
    latency_ms: list[float] = field(default_factory=list)  # per estimate with a next frame (see the module doc)
    forces: list[tuple[int, np.ndarray]] = field(default_factory=list)  # (stamp_ns, force N) as sent
    bands: list[np.ndarray] = field(default_factory=list)  # each sent force's band half-width (3,) N
    beyond: int = 0  # estimates with a component beyond the training range
    unfamiliar: int = 0  # estimates whose input is unlike training's (vfmodels.evaluation.band.unfamiliar)

    @property
    def rate_fps(self) -> float:
        return self.estimates / self.wall_s if self.wall_s > 0 else 0.0

    def summary(self) -> dict[str, float]:
        lat = np.asarray(self.latency_ms) if self.latency_ms else np.full(1, np.nan)
        return {"frames": self.frames, "estimates": self.estimates, "dropped": self.dropped, "beyond": self.beyond,
                "unfamiliar": self.unfamiliar,
                "rate_fps": round(self.rate_fps, 2), "latency_median_ms": round(float(np.median(lat)), 1),
                "latency_p95_ms": round(float(np.percentile(lat, 95)), 1)}


class LiveSession:
    """Connects a source, an estimator and a server (see the module docstring). `run()` returns when
    the source ends, `max_frames` are in, or `stop` is set; the caller closes the server."""

    def __init__(self, source, estimator: StreamingForceEstimator, server: FoxgloveServer,
                 stop: threading.Event | None = None):
        self.source, self.estimator, self.server = source, estimator, server
        self.stop = stop or threading.Event()
        self.stats = LiveStats()
        self._tracked: list[FrameResult] = []
        self.object_frame: ObjectFrame | None = None  # the stream's (the estimator forgets it at its flush)
        self._arrivals: dict[int, float] = {}  # stamp -> arrival of the next frame (the velocity's)
        self._last: LiveFrame | None = None
        self.lean: dict[str, str] = {}  # the lean metadata (vfdata.tissue_lean), set at the first estimate
        self.doubtful_since_ns: int | None = None  # the first estimate made while the stream was doubtful
        estimator.on_frame = self._on_frame

    def _on_frame(self, result: FrameResult) -> None:
        self.object_frame = self.estimator.frame
        self._tracked.append(result)

    def run(self) -> LiveStats:
        first_arrival = None
        try:
            for frame in self.source:
                if first_arrival is None:
                    first_arrival = frame.arrival_s
                if self._last is not None:
                    self._arrivals[self._last.stamp_ns] = frame.arrival_s
                self._last = frame
                self.stats.frames += 1
                estimate = self.estimator.push(frame.left, frame.right, frame.stamp_ns, frame.depth_mm)
                self._send(estimate)
                if self.stop.is_set():
                    break
            for estimate in self.estimator.flush():
                self._send(estimate)
            self._send(None)  # the frames flush tracked
        finally:
            self.stats.dropped = int(getattr(self.source, "dropped", 0))
            if first_arrival is not None:
                self.stats.wall_s = time.perf_counter() - first_arrival
        return self.stats

    def _send(self, estimate: ForceEstimate | None) -> None:
        if estimate is not None:
            force, stamp = np.asarray(estimate.force_n, dtype=np.float64), int(estimate.stamp_ns)
            self.server.publish(layout.FORCE_ESTIMATE, wrench_of(stamp, force))
            sent = time.perf_counter()
            self.server.publish(layout.FORCE_BAND, wrench_of(stamp, estimate.band_n))
            self.server.publish(layout.FORCE_BEYOND, wrench_of(stamp, estimate.beyond_n))
            self.server.publish(layout.FORCE_UNLIKE, Float64(estimate.unlike), log_time_ns=stamp)
            arrival = self._arrivals.pop(int(estimate.stamp_ns), None)
            if arrival is not None:
                self.stats.latency_ms.append(1000.0 * (sent - arrival))
            if self.stats.estimates == 0:  # the object frame is fixed: its lean is known (recorded, not said)
                self.lean = self.estimator.lean[1]
            self.stats.estimates += 1
            self.stats.forces.append((stamp, force))
            self.stats.bands.append(np.asarray(estimate.band_n, dtype=np.float64))
            self.stats.beyond += int(estimate.beyond_training)
            self.stats.unfamiliar += int(estimate.unfamiliar)
            if estimate.doubtful and self.doubtful_since_ns is None:
                self.doubtful_since_ns = stamp
                print(f"warning: live: doubtful from frame stamp {estimate.stamp_ns}: "
                      f"{self.estimator.confidence.describe()}", file=sys.stderr, flush=True)
        while self._tracked:
            self._send_frame(self._tracked.pop(0))

    def _send_frame(self, result: FrameResult) -> None:
        server, stamp, frame = self.server, result.stamp_ns, self.object_frame
        rig = self.source.rig
        camera_frame = rig.camera_frame_id
        server.publish(layout.TF, object_tf(frame.rotation, frame.origin, stamp, camera_frame))
        for topic, message in rig.view_messages(stamp, result.left, result.depth_mm, server.wants):
            server.publish(topic, message)
        if server.wants(layout.TISSUE_MASK):
            server.publish(layout.TISSUE_MASK, mask_message(result.mask, stamp, camera_frame))
        if server.wants(layout.TISSUE_POINTS):
            server.publish(layout.TISSUE_POINTS, cloud_message(frame.to_object(result.cloud_mm), stamp))
        if result.points_mm is not None and server.wants(layout.TRACKING_POINTS):
            server.publish(layout.TRACKING_POINTS,
                           cloud_message(frame.to_object(result.points_mm), stamp, result.visible))

    def metadata(self) -> dict[str, str]:
        """The `visionforce.derived` record of a recorded session (readable as a force file)."""
        frame = self.object_frame
        calibration = self.estimator.regressor.band_calibration
        meta = {"stage": "live", "derived_version": str(DERIVED_VERSION), "torque_estimated": "false",
                "live_stats": json.dumps(self.stats.summary()),
                "band": json.dumps(None if calibration is None else calibration.to_dict())}
        if frame is not None:
            meta["object_frame"] = json.dumps(frame.to_dict())
            meta["up_known"] = str(self.source.rig.up is not None).lower()
            meta["object_frame_kind"] = frame.kind
            meta["x_axis"] = x_axis_meaning(meta["object_frame_kind"], self.source.rig.up is not None)
        meta["camera_frame_id"] = self.source.rig.camera_frame_id
        meta.update(self.lean)
        confidence = self.estimator.confidence
        if confidence is not None:
            meta.update(confidence.metadata())
            if self.doubtful_since_ns is not None:
                meta["doubtful_since_ns"] = str(self.doubtful_since_ns)
        return meta
