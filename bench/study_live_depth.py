"""What cheaper depth costs the live estimator: rate against accuracy, for a depth region of interest
(`EngineOptions.depth_roi_margin_px`) and coarser / lighter SGBM settings, before choosing a live default.

    python bench/study_live_depth.py [--frames 60] [--recording REC.mcap] [--ckpt CKPT]

For each variant, the serial streaming estimator runs over the same frames of a simulated recording
(one thread per stage) and the study prints: CPU ms/frame of depth and of the whole frame; the depth
error against the simulator's true depth inside the true tissue mask (median and p90 of |error|, mm;
the pixels the cloud and the tracker use); the tracked points' change against the whole-image
variant (mm; only where the first frame, always whole-image, gives the same points: not for other
SGBM settings, whose first frame differs); the force's change against it (RMSE, N; with an
untrained model, without --ckpt, it shows how much the input moved, not a force error); and, for the SGBM settings,
the end-point error on the SCARED frame (../shared/data/scared, px; the region of interest does not
change the matching inside it, so it has none of its own).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_pipeline import simulated_recording, untrained_checkpoint  # noqa: E402

SCARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "scared"
VARIANTS = {
    "whole image (default)": {},
    "roi, margin 24 px": {"depth_roi_margin_px": 24},
    "roi, margin 48 px": {"depth_roi_margin_px": 48},
    "sgbm scale 0.4": {"depth_options": {"scale": 0.4}},
    "sgbm no refinement": {"depth_options": {"refine_window": 0}},
    "roi 24 + sgbm scale 0.4": {"depth_roi_margin_px": 24, "depth_options": {"scale": 0.4}},
}


def scared_epe(depth_options: dict) -> float:
    if not (SCARED / "left.png").is_file():
        return float("nan")
    from vfdata.recon import make_depth_estimator

    left, right = cv2.imread(str(SCARED / "left.png")), cv2.imread(str(SCARED / "right.png"))
    gt = cv2.imread(str(SCARED / "disparity.tiff"), cv2.IMREAD_UNCHANGED)
    valid = (gt > 0) & (cv2.imread(str(SCARED / "occlusion.png"), cv2.IMREAD_UNCHANGED) != 128)
    disp = make_depth_estimator("sgbm", max_disparity=96, **depth_options).disparity(left, right)
    given = valid & np.isfinite(disp) & (disp > 0)
    return float(np.abs(disp - gt)[given].mean())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--recording", type=Path, help="simulated recording MCAP (default: simulate mini)")
    parser.add_argument("--ckpt", type=Path, help="trained checkpoint (default: untrained)")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "vf_bench_pipeline")
    args = parser.parse_args()

    from vfdata.engine import EngineOptions, recorded_depths, recorded_masks
    from vfdata.recording import Recording
    from vfdata.rig import StereoRig, camera_up, recording_prompt
    from vfmodels.inference.live import StreamingForceEstimator

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    args.workdir.mkdir(parents=True, exist_ok=True)
    recording = args.recording or simulated_recording(args.workdir, max(args.frames, 30))
    ckpt = args.ckpt or untrained_checkpoint(args.workdir / "untrained.ckpt")
    with Recording.open(recording) as rec:
        n = min(args.frames, rec.num_frames)
        frames = [rec.rectified_frame(i) for i in range(n)]
        camera, baseline, up = rec.camera, rec.stereo.baseline_mm, camera_up(rec)
        prompt = recording_prompt(rec, recording, None)
        truth = Path(rec.metadata.source) / "ground_truth"
    true_depths = [d for _, d in zip(range(n), recorded_depths(truth), strict=False)]
    true_masks = [m for _, m in zip(range(n), recorded_masks(truth), strict=False)]

    print(f"{recording}: {n} frames {camera.width}x{camera.height}, serial, one thread per stage")
    print(f"{'variant':26s}{'depth ms':>9s}{'frame ms':>9s}{'err med':>8s}{'err p90':>8s}{'tracks':>8s}"
          f"{'force':>8s}{'SCARED':>8s}")
    reference = None
    for label, options in [("(warm-up, not shown)", {}), *VARIANTS.items()]:
        cv2.setRNGSeed(0)
        rig = StereoRig(recording, camera=camera, baseline_mm=baseline, up=up)
        estimator = StreamingForceEstimator(ckpt, rig, prompt, EngineOptions(**options))
        depths, points = [], []
        estimator.on_frame = lambda r, d=depths, p=points: (d.append(r.depth_mm), p.append(r.points_mm))
        forces = [e.force_n for f in frames if (e := estimator.push(f.left, f.right, f.stamp_ns)) is not None]
        forces += [e.force_n for e in estimator.flush()]
        cpu = estimator.stage_cpu_seconds
        errors = np.concatenate([np.abs(d - t)[m & np.isfinite(d) & np.isfinite(t)]
                                 for d, t, m in zip(depths[1:], true_depths[1:], true_masks[1:], strict=True)])
        forces, points = np.array(forces), np.array(points)
        estimator.close()
        if label.startswith("(warm-up"):
            continue
        if reference is None:
            reference = (forces, points)
        # Point by point only when the first frame (its whole-image depth: the sampled points) is the same.
        same_start = np.allclose(points[0], reference[1][0], equal_nan=True)
        track_change = float(np.nanmean(np.linalg.norm(points - reference[1], axis=-1))) if same_start else np.nan
        force_change = float(np.sqrt(np.mean((forces - reference[0]) ** 2)))
        epe = scared_epe(options.get("depth_options", {})) if "roi" not in label or "scale" in label else \
            float("nan")
        print(f"{label:26s}{1000 * cpu['depth'] / n:9.1f}{1000 * sum(cpu.values()) / n:9.1f}"
              f"{np.median(errors):8.2f}{np.percentile(errors, 90):8.2f}{track_change:8.3f}{force_change:8.4f}"
              f"{epe:8.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
