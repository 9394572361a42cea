"""Do the forces a user gets equal the forces the experiment scored? One run of `vfdata experiment`
against the `/force/estimate` files of `vfdata predict`, `--stream` or `vfdata live --record` on one of
its test recordings (the same checkpoint).

    python bench/study_parity.py RESULTS/runs/visionforce/seed0 OUT/mini_002.force.mcap [MORE.force.mcap ...]

For each force file it prints the RMSE against the sensor (the test's measured force at the same frames;
the average of Fx, Fy, Fz, as Table I), the experiment's own RMSE on the recording, and how far the file's
forces are from the scored ones: on every frame, and on the frames where both define the same clip (the
test scores a frame from the stride-4 clip it ends latest in; `vfdata predict` from the latest 16-frame
clip ending at it: the same clip at the first 16 frames and at every clip's last frame).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from vfdata.clips.tokens import clip_starts, segments
from vfdata.recording.derived import read_force_estimate
from vfmodels.evaluation.metrics import force_metrics


def scored_clip_starts(times_ns: np.ndarray, clip_frames: int, stride: int) -> np.ndarray:
    """Per frame, the first frame of the clip the test scores it from (its latest position), -1 if none."""
    out = np.full(len(times_ns), -1, dtype=np.int64)
    for start in clip_starts(segments(times_ns), clip_frames, stride)[::-1]:  # the smallest start wins
        out[start:start + clip_frames] = start
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a finished run folder of `vfdata experiment` (predictions.npz)")
    parser.add_argument("forces", type=Path, nargs="+", help="force files on one of its test recordings")
    parser.add_argument("--clip-frames", type=int, default=16)
    parser.add_argument("--stride", type=int, default=4)
    args = parser.parse_args()
    scored = dict(np.load(args.run / "predictions.npz", allow_pickle=False))
    summary = json.loads((args.run / "metrics.json").read_text())
    print(f"{args.run}: checkpoint {summary.get('checkpoint')}")
    for path in args.forces:
        times, force = read_force_estimate(path)
        rows = np.flatnonzero(np.isin(scored["frame_time_ns"], times))
        recording = set(scored["recording"][rows].tolist())
        if len(recording) != 1:
            print(f"{path}: not one test recording of the run ({sorted(recording)})")
            return 1
        rows = rows[np.argsort(scored["frame_time_ns"][rows])]
        at = np.searchsorted(times, scored["frame_time_ns"][rows])
        mine, test, true = force[at], scored["pred"][rows], scored["true"][rows]
        index = np.searchsorted(times, scored["frame_time_ns"][rows])
        same = scored_clip_starts(times, args.clip_frames, args.stride)[index] == np.maximum(
            0, index - args.clip_frames + 1)
        diff = np.abs(mine - test)
        print(f"{path} ({recording.pop()}, {len(rows)} scored frames):")
        print(f"  RMSE against the sensor: this file {force_metrics(mine, true)['rmse']:.4f} N, "
              f"the experiment's test {force_metrics(test, true)['rmse']:.4f} N")
        print(f"  |this - test| on every frame: max {diff.max():.4f} N, mean {diff.mean():.4f} N")
        print(f"  on the {int(same.sum())} frames of the same clip: max {diff[same].max():.2e} N")
    return 0


if __name__ == "__main__":
    sys.exit(main())
