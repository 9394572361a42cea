"""Running the trackers on a simulated raw recording and scoring them against its ground truth.

The tissue clouds are made from the simulator's ground-truth depth and mask (so the scores isolate the
tracker from the reconstruction), sub-sampled to a fixed size as the processing pipeline does. The
scores are those of `vfdata.metrics`: 3D error split along the true surface normal, and coverage and
NNI at the force peaks.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from vfdata import metrics
from vfdata.calibration import PinholeCamera, StereoCalibration
from vfdata.errors import InputError
from vfdata.tracking.groundtruth import ground_truth_tracks
from vfdata.tracking.registry import TRACKERS, FrameInputs, make_tracker


@dataclass
class SimRecording:
    """A simulated raw recording folder, read lazily frame by frame."""

    folder: Path
    camera: PinholeCamera
    material_points: np.ndarray  # (F, P, 3) mm
    material_normals: np.ndarray  # (F, P, 3)
    force_n: np.ndarray  # (F, 3) per frame
    baseline_mm: float = 0.0  # the rectified pair's

    @classmethod
    def open(cls, folder: str | Path) -> SimRecording:
        folder = Path(folder)
        gt = folder / "ground_truth"
        for needed in ("calibration.yaml", "ground_truth/points.npy", "ground_truth/normals.npy"):
            if not (folder / needed).is_file():
                raise InputError(folder, f"not a simulated recording (no {needed})")
        rectified = StereoCalibration.load(folder / "calibration.yaml").rectified
        points = np.load(gt / "points.npy")
        normals = np.load(gt / "normals.npy")
        force = np.load(gt / "force.npy") if (gt / "force.npy").is_file() else np.zeros((len(points), 3))
        return cls(folder, rectified.left, points, normals, force, rectified.baseline_mm)

    @property
    def num_frames(self) -> int:
        return len(self.material_points)

    def image(self, frame: int, view: str = "left") -> np.ndarray:
        """(H, W, 3) uint8 BGR image of `view` (left or right; OpenCV order, as `Recording.frame` gives);
        PNG or JPEG. The simulator renders rectified views."""
        path = self.folder / view / f"{frame:06d}.png"
        if not path.is_file():
            path = path.with_suffix(".jpg")
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise InputError(path, "missing or unreadable image")
        return bgr

    def mask(self, frame: int) -> np.ndarray:
        return cv2.imread(str(self.folder / "ground_truth/mask" / f"{frame:06d}.png"), cv2.IMREAD_UNCHANGED) > 0

    def depth_mm(self, frame: int) -> np.ndarray:
        raw = cv2.imread(str(self.folder / "ground_truth/depth" / f"{frame:06d}.png"), cv2.IMREAD_UNCHANGED)
        return raw.astype(np.float32) / 10.0  # stored in 0.1 mm, 0 = none

    def truly_visible(self, points: np.ndarray, frame: int) -> np.ndarray:
        """(N,) bool: true positions (N, 3) mm that the camera sees at `frame`: inside the tissue mask
        and at the depth of the rendered surface there (the simulator's own visibility test)."""
        depth = self.depth_mm(frame)
        uv = self.camera.project(points)
        inside = self.camera.in_mask(points, self.mask(frame))
        u = np.floor(uv[inside, 0] + 0.5).astype(np.int64)
        v = np.floor(uv[inside, 1] + 0.5).astype(np.int64)
        z = points[inside, 2]
        seen = np.zeros(len(points), dtype=bool)
        seen[inside] = np.abs(depth[v, u] - z) < 0.3 + 0.01 * z
        return seen

    def cloud(self, frame: int, num_points: int = 20000, seed: int = 0) -> np.ndarray:
        """The tissue cloud (M <= num_points, 3) mm: masked ground-truth depth, back-projected."""
        cloud = self.camera.backproject(self.depth_mm(frame), self.mask(frame))
        if len(cloud) > num_points:
            cloud = cloud[np.random.default_rng((seed, frame)).choice(len(cloud), num_points, replace=False)]
        return cloud


@dataclass
class TrackingRun:
    name: str
    points: np.ndarray  # (F, n, 3) mm, NaN where a tracker gave none
    visible: np.ndarray  # (F, n) bool
    seconds: float  # wall time of the updates alone
    cpu_seconds: float  # process CPU time of the updates alone
    scores: dict = field(default_factory=dict)

    @property
    def frames_per_second(self) -> float:
        return (len(self.points) - 1) / max(self.seconds, 1e-9)

    @property
    def cpu_frames_per_second(self) -> float:
        return (len(self.points) - 1) / max(self.cpu_seconds, 1e-9)


def run_tracker(
    name: str,
    rec: SimRecording,
    num_points: int = 256,
    cloud_points: int = 20000,
    seed: int = 0,
    frames: int | None = None,
    progress: bool = False,
    **options,
) -> TrackingRun:
    """Track `num_points` points through the first `frames` frames of `rec` with tracker `name`
    (one of TRACKERS; `options` go to it). The timings count the tracker's own work only: reading
    the frame's inputs is left out, and an offline tracker is timed on the whole clip."""
    if name not in TRACKERS:
        raise ValueError(f"unknown tracker {name!r} (choose from {', '.join(TRACKERS)})")
    count = rec.num_frames if frames is None else min(frames, rec.num_frames)
    first = FrameInputs(index=0, camera=rec.camera, image_bgr=rec.image(0), depth_mm=rec.depth_mm(0),
                        mask=rec.mask(0), cloud_mm=rec.cloud(0, cloud_points, seed), right_bgr=rec.image(0, "right"),
                        baseline_mm=rec.baseline_mm)
    tracker = make_tracker(name, first, num_points, seed,
                           ground_truth=(rec.material_points, rec.material_normals), **options)
    points, visible = [tracker.points], [tracker.visible]
    wall = cpu = 0.0
    for f in tqdm(range(1, count), desc=name, disable=not progress, leave=False):
        frame = _frame_inputs(rec, f, tracker.inputs, cloud_points, seed)
        t0, c0 = time.perf_counter(), time.process_time()
        if tracker.offline:
            tracker.collect(frame)
        else:
            p, v = tracker.update(frame)
            points.append(p)
            visible.append(v)
        wall += time.perf_counter() - t0
        cpu += time.process_time() - c0
    if tracker.offline:
        t0, c0 = time.perf_counter(), time.process_time()
        all_points, all_visible = tracker.finish()
        wall += time.perf_counter() - t0
        cpu += time.process_time() - c0
        points, visible = list(all_points), list(all_visible)
    return TrackingRun(name, np.stack(points), np.stack(visible), wall, cpu)


def _frame_inputs(rec: SimRecording, frame: int, needed: frozenset[str], cloud_points: int, seed: int) -> FrameInputs:
    """The inputs of `frame` that a tracker reads (reading the others would only cost time)."""
    return FrameInputs(
        index=frame,
        camera=rec.camera,
        image_bgr=rec.image(frame) if "image_bgr" in needed else None,
        depth_mm=rec.depth_mm(frame) if "depth_mm" in needed else None,
        mask=rec.mask(frame),
        cloud_mm=rec.cloud(frame, cloud_points, seed) if "cloud_mm" in needed else None,
        right_bgr=rec.image(frame, "right") if "right_bgr" in needed else None,
        baseline_mm=rec.baseline_mm,
    )


def score(run: TrackingRun, rec: SimRecording) -> dict:
    """Error against ground truth over every frame and point the tracker reports (and, as `seen_*`,
    over those whose true position is in view: in the mask and not behind another surface), and coverage / NNI
    at the force peaks (when the clip has none: every 30th frame back from the last). Frame 0 of the run holds the
    reference selection, the same for every tracker. NNI is in 3D (mm) over the points visible at both frames;
    `nni_image` is the same ratio for their projections in the left image (pixels)."""
    count = len(run.points)
    truth, normals = ground_truth_tracks(run.points[0], rec.material_points[:count], rec.material_normals[:count])
    error = metrics.tracking_error(run.points, truth, normals)
    seen = np.stack([rec.truly_visible(truth[f], f) for f in range(count)])
    error_seen = metrics.tracking_error(run.points, truth, normals, valid=seen)
    peaks = metrics.force_peaks(rec.force_n[:count])
    judged = peaks if len(peaks) else np.arange(count - 1, 0, -30)[::-1]
    cover, nni, nni_image = [], [], []
    first_uv = rec.camera.project(run.points[0])
    for f in judged:
        uv = rec.camera.project(run.points[f])
        cover.append(metrics.coverage(uv, rec.mask(f), run.visible[f]))
        nni.append(metrics.nearest_neighbour_index(run.points[f], run.points[0], run.visible[f], run.visible[0]))
        nni_image.append(metrics.nearest_neighbour_index(uv, first_uv, run.visible[f], run.visible[0]))
    lost = float(np.mean(~np.isfinite(run.points[-1]).all(axis=1)))
    return {
        **error.as_dict(),
        **{f"seen_{k}": v for k, v in error_seen.as_dict().items()},
        "coverage": float(np.mean(cover)) if cover else float("nan"),
        "nni": float(np.nanmean(nni)) if nni else float("nan"),
        "nni_image": float(np.nanmean(nni_image)) if nni_image else float("nan"),
        "peaks": len(peaks),
        "lost_at_end": lost,
        "fps": run.frames_per_second,
        "cpu_fps": run.cpu_frames_per_second,
    }
