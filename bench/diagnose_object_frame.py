"""Where the object-frame representation breaks on a simulated study (issue 7, colon): prints, per
recording, figures that need only the simulator's ground truth and the processed files.

    python bench/diagnose_object_frame.py datasets/colon.manifest.yaml [--results results/colon]

1. Estimated object frame (processing metadata) vs the simulator's (`ground_truth/object_frame.json`):
   angle of Z and of X (deg), origin offset (mm, along the true Z and across it), and whether +Z runs
   wide -> narrow (the angle of Z is then < 90 deg).
2. Label frame: the force (sensor frame) regressed on the mean displacement of all 2000 material points
   in the true object frame; the same signs and similar gains (N/mm) at every orientation mean the
   labels turn with the object, as they should.
3. Token distribution: mean and std of the visible material points at frame 0 in the true object
   frame, the estimated object frame and the camera frame (mm).
4. Tracker drift: mean error (tracked - true, estimated object frame, mm) of the visible geometry
   tracks, and its median norm, per quarter of the recording.
5. With --results: each variant's mean prediction vs the mean truth per test recording, and its
   RMSE after removing each recording's mean error (N).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from vfdata.manifest import load_manifest
from vfdata.recording.derived import read_tracks
from vfdata.tracking import ground_truth_tracks


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def fmt(v: np.ndarray, digits: int = 1) -> str:
    return "(" + ", ".join(f"{x:6.{digits}f}" for x in np.asarray(v)) + ")"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("manifest", type=Path)
    parser.add_argument("--results", type=Path, help="results folder with runs/proposed/seed0/predictions.npz")
    args = parser.parse_args()
    entries = list(load_manifest(args.manifest).entries)

    print("1. object frame: estimated vs true")
    print(f"{'recording':>10} {'deg':>4} {'Z err':>6} {'X err':>6} {'|origin|':>8} {'along Z':>7} {'across':>6}")
    frames = {}
    for e in entries:
        gt = json.loads((e.raw / "ground_truth" / "object_frame.json").read_text())
        est = read_tracks(e.processed).frame
        r_true, o_true = np.array(gt["rotation"]), np.array(gt["origin_mm"])
        r_est, o_est = est.rotation, est.origin
        frames[e.id] = (r_true, o_true, r_est, o_est)
        offset = o_est - o_true
        along = float(offset @ r_true[:, 2])
        across = float(np.linalg.norm(offset - along * r_true[:, 2]))
        print(f"{e.id:>10} {e.orientation_deg:4.0f} {angle_deg(r_est[:, 2], r_true[:, 2]):6.1f} "
              f"{angle_deg(r_est[:, 0], r_true[:, 0]):6.1f} {np.linalg.norm(offset):8.1f} {along:7.1f} {across:6.1f}")

    print("\n2. label frame: force ~ mean material displacement (true object frame); diagonal gains N/mm, R^2")
    print("3. visible material points at frame 0: mean and std (mm) per frame")
    for e in entries:
        gt = e.raw / "ground_truth"
        points = np.load(gt / "points.npy").astype(np.float64)
        visible = np.load(gt / "visible.npy")
        force = np.load(gt / "force.npy")[:, :3].astype(np.float64)
        r_true, o_true, r_est, o_est = frames[e.id]
        true_obj = (points - o_true) @ r_true
        disp = (true_obj - true_obj[:1]).mean(axis=1)
        design = np.c_[disp, np.ones(len(disp))]
        gains, *_ = np.linalg.lstsq(design, force, rcond=None)
        r2 = 1 - ((design @ gains - force) ** 2).sum(0) / ((force - force.mean(0)) ** 2).sum(0)
        vis = visible[0]
        est_obj = (points[0] - o_est) @ r_est
        print(f"{e.id} ({e.orientation_deg:.0f} deg): gains {fmt(np.diag(gains[:3]), 2)} R^2 {fmt(r2, 2)}")
        for name, p in (("true object", true_obj[0]), ("est. object", est_obj), ("camera", points[0])):
            print(f"    {name:>11}: mean {fmt(p[vis].mean(0))} std {fmt(p[vis].std(0))}")

    print("\n4. geometry-tracker drift (tracked - true, estimated object frame, mm) per quarter")
    for e in entries:
        gt = e.raw / "ground_truth"
        tracks = read_tracks(e.processed)
        rotation, origin = tracks.frame.rotation, tracks.frame.origin
        cam = tracks.points_object_mm @ rotation.T + origin
        truth, _ = ground_truth_tracks(cam[0], np.load(gt / "points.npy", mmap_mode="r"),
                                       np.load(gt / "normals.npy", mmap_mode="r"))
        n = min(len(cam), len(truth))
        err = tracks.points_object_mm[:n] - (truth[:n] - origin) @ rotation
        parts = []
        for q in range(4):
            s = slice(q * n // 4, (q + 1) * n // 4)
            e_q = err[s][tracks.visible[:n][s]]
            parts.append(f"{fmt(e_q.mean(0))} |{np.median(np.linalg.norm(e_q, axis=1)):4.1f}|")
        print(f"{e.id} ({e.orientation_deg:.0f} deg): " + "  ".join(parts))

    if args.results is not None:
        print("\n5. each finished variant (seed 0) per test recording (N)")
        for variant in sorted(p.name for p in (args.results / "runs").iterdir()):
            path = args.results / "runs" / variant / "seed0" / "predictions.npz"
            if not path.is_file():
                continue
            pred = dict(np.load(path))
            ok = np.isfinite(pred["true"]).all(axis=1)
            error = pred["pred"][ok] - pred["true"][ok]
            recordings = pred["recording"][ok]
            for r in np.unique(recordings):
                k = recordings == r
                print(f"{variant:>25} {r}: mean pred {fmt(pred['pred'][ok][k].mean(0), 2)} "
                      f"true {fmt(pred['true'][ok][k].mean(0), 2)}")
                error[k] -= error[k].mean(0)
            rmse = np.sqrt((error**2).mean(0))
            print(f"{variant:>25} RMSE without each recording's mean error: {fmt(rmse, 2)} avg {rmse.mean():.3f}")


if __name__ == "__main__":
    main()
