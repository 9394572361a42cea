"""Depth along the line of sight (issue 32, item 5): the `klt` tracker's lifts against the simulator's truth.

    python bench/study_stereo_lift.py DATA [DATA ...] [--lifts depth stereo stereo:0.5] [--frames N] [--all]
    python bench/study_stereo_lift.py --summary A.json B.json ...      # the means of earlier --json runs

DATA: a `vfdata synth` folder; its test recordings are studied (--all: every recording). Each raw folder
is converted to MCAP once (kept beside it as <id>.mcap) and run through the engine as `vfdata process`
runs it (sgbm depth, colortrack mask, `klt` with 256 points, seed 0), in the camera frame, once per lift:
`depth` (the depth map read at each tracked pixel), `stereo` (each point's own match in the right image,
triangulated); `LIFT:A` filters each point's depth over time (klt's `smoothing` A in [0, 1)); `truedepth`
reads the simulator's true depth map (and its mask follows that depth): what a perfect depth would give
the same 2D tracker, a bound.

Against the simulator's material points carried to the same reference points (`ground_truth_tracks`),
with Z the true object frame's axis (ground_truth/object_frame.json) and displacements from frame 0:
  3d_rms     RMS of the 3D position error over every frame and visible point (mm)
  z_rms      RMS of the error of the Z displacement (mm); z_med: its median size; truth_z: RMS of the
             true Z displacement
  corr_z     correlation over frames of the mean Z displacement of the visible points, tracked vs true
  xy_rms     RMS of the error of the X and Y displacement (mm, the plane across the axis)
  stereo     share of the visible point-frames lifted by their stereo match (the rest: the depth map)
`into` is how far the tube's axis runs into depth at frame 0 (degrees from the image plane).

Seeds: tune on none of the seeds you report; docs/tracking.md lists the seeds the figures came from.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vfdata.conversion.options import ConvertOptions
from vfdata.conversion.raw_folder import convert_raw_folder
from vfdata.engine import EngineOptions
from vfdata.manifest import load_manifest
from vfdata.recording import Recording
from vfdata.rig import rig_for
from vfdata.threads import thread_limit
from vfdata.tracking.groundtruth import ground_truth_tracks

COLUMNS = ("3d_rms", "z_rms", "z_med", "truth_z", "corr_z", "xy_rms", "stereo")


@dataclass
class Lift:
    name: str
    options: dict
    depth: str = "sgbm"  # "recorded": the simulator's true depth map (a bound, not a method)

    @classmethod
    def parse(cls, text: str) -> Lift:
        kind, _, smoothing = text.partition(":")
        options = {"lift": "depth" if kind == "truedepth" else kind}
        if smoothing:
            options["smoothing"] = float(smoothing)
        return cls(text, options, "recorded" if kind == "truedepth" else "sgbm")


def recordings(data: Path, every: bool) -> list[tuple[str, float, Path]]:
    """(id, orientation degrees, raw folder) of the dataset's test recordings (or all of them)."""
    manifest = load_manifest(next(data.glob("*.manifest.yaml")))
    return [(e.id, float(e.orientation_deg or 0.0), Path(e.raw)) for e in manifest.entries
            if every or e.split == "test"]


def mcap_of(raw: Path) -> Path:
    out = raw.with_name(raw.name + ".mcap")
    if not out.is_file():
        convert_raw_folder(raw, out, options=ConvertOptions(progress=False))
    return out


def track(mcap: Path, lift: Lift, frames: int | None, ground_truth: Path | None = None
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The klt tracks in the left camera frame: points (F, n, 3) mm, visible (F, n), stereo (F, n)."""
    rec = Recording.open(mcap)
    count = rec.num_frames if frames is None else min(frames, rec.num_frames)
    options = EngineOptions(tracker="klt", tracker_options=lift.options, object_frame="camera", depth=lift.depth)
    rig = rig_for(rec, mcap)
    engine = rig.engine(options, rig.prompt(None), ground_truth, look_ahead=count)
    points, visible, stereo = [], [], []
    for result in engine.run(rig.frames(count)):
        points.append(result.points_mm)
        visible.append(result.visible)
        stereo.append(getattr(engine.tracker._tracker, "from_stereo", np.zeros(len(result.visible), bool)).copy())
    return np.stack(points), np.stack(visible), np.stack(stereo)


def scores(points: np.ndarray, visible: np.ndarray, stereo: np.ndarray, raw: Path) -> dict[str, float]:
    gt = raw / "ground_truth"
    count = len(points)
    truth, _ = ground_truth_tracks(points[0], np.load(gt / "points.npy")[:count], np.load(gt / "normals.npy")[:count])
    frame = json.loads((gt / "object_frame.json").read_text())
    rotation = np.asarray(frame["rotation"], dtype=np.float64)  # columns: the object axes in the camera frame
    ok = visible & np.isfinite(points).all(axis=-1) & visible[:1]
    error = np.linalg.norm(points - truth, axis=-1)[ok]
    shift = (points - points[:1]) @ rotation  # object-frame displacements
    true_shift = (truth - truth[:1]) @ rotation
    dz = (shift - true_shift)[..., 2][ok]
    dxy = (shift - true_shift)[..., :2][ok]
    mean_z = np.array([shift[f, ok[f], 2].mean() if ok[f].any() else np.nan for f in range(count)])
    true_mean_z = np.array([true_shift[f, ok[f], 2].mean() if ok[f].any() else np.nan for f in range(count)])
    both = np.isfinite(mean_z) & np.isfinite(true_mean_z)
    return {"3d_rms": float(np.sqrt(np.mean(error ** 2))), "z_rms": float(np.sqrt(np.mean(dz ** 2))),
            "z_med": float(np.median(np.abs(dz))),
            "truth_z": float(np.sqrt(np.mean(true_shift[..., 2][ok] ** 2))),
            "corr_z": float(np.corrcoef(mean_z[both], true_mean_z[both])[0, 1]),
            "xy_rms": float(np.sqrt(np.mean(np.sum(dxy ** 2, axis=-1)))),
            "stereo": float(stereo[ok].mean()), "into_deg": float(np.degrees(np.arcsin(abs(rotation[2, 2]))))}


BANDS = ((0.0, 20.0, "frontal, into < 20"), (20.0, 40.0, "into 20-40"), (40.0, 90.0, "into 40-60+"))


def summary(rows: list[dict], lifts: list[str]) -> None:
    """Means over the recordings of each band of `into` (how far the tube runs into depth), then all."""
    for lo, hi, label in (*BANDS, (0.0, 90.0, "all")):
        band = [r for r in rows if lo <= r["into_deg"] < hi]
        if not band:
            continue
        print(f"\nmean over {len({(r['data'], r['recording']) for r in band})} recordings, {label} degrees")
        for lift in lifts:
            mine = [r for r in band if r["lift"] == lift]
            print(f"{'':<40}{lift:<12}" + "".join(f"{np.mean([r[c] for r in mine]):>9.3f}" for c in COLUMNS))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", nargs="*", type=Path, help="vfdata synth folders")
    parser.add_argument("--lifts", nargs="+", default=["depth", "stereo"])
    parser.add_argument("--frames", type=int, default=None, help="only the first N frames of each recording")
    parser.add_argument("--all", action="store_true", help="every recording, not only the test ones")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.add_argument("--summary", nargs="+", type=Path, help="only print the summary of these --json files")
    args = parser.parse_args()
    if args.summary:
        rows = [r for path in args.summary for r in json.loads(path.read_text())]
        return summary(rows, list(dict.fromkeys(r["lift"] for r in rows)))
    lifts = [Lift.parse(t) for t in args.lifts]
    print(f"load average {os.getloadavg()[0]:.1f}; lifts {', '.join(lift.name for lift in lifts)}")
    print(f"{'recording':<28}{'view':>6}{'into':>6}  {'lift':<12}" + "".join(f"{c:>9}" for c in COLUMNS))
    rows = []
    with thread_limit(1):
        for data in args.data:
            for rec_id, view, raw in recordings(data, args.all):
                mcap = mcap_of(raw)
                for lift in lifts:
                    started = time.perf_counter()
                    row = scores(*track(mcap, lift, args.frames, raw / "ground_truth"), raw)
                    row.update(data=str(data), recording=rec_id, view=view, lift=lift.name,
                               seconds=time.perf_counter() - started)
                    rows.append(row)
                    print(f"{data.name + '/' + rec_id:<28}{view:>6.0f}{row['into_deg']:>6.0f}  {lift.name:<12}"
                          + "".join(f"{row[c]:>9.3f}" for c in COLUMNS), flush=True)
    summary(rows, [lift.name for lift in lifts])
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    sys.exit(main())
