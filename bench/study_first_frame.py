"""The first frame's mask and object frame against the simulator's truth, per recording (issue 32's fast
loop): converts each raw recording of a synthesized dataset, runs depth, mask and object frame on its first
frame(s) (no tracking) and prints the mask IoU, the Z-axis error (deg) and the origin offset (mm). Where the
object frame looked again at the frames where the tissue rests (`vfdata.recon.rest_frames`: full-length
recordings), it also prints the error of the first frame's fit alone, and the error against the tissue's
own axis (`sweep.droop_figures`) of both.

    vfdata synth --preset colon --seed 11 --frames 90 --test-orientations 60,135,270 data/dev11
    python bench/study_first_frame.py data/dev11/colon.manifest.yaml [--save-masks DIR]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
from sweep import droop_figures

from vfdata.conversion.raw_folder import convert_raw_folder
from vfdata.engine import EngineOptions
from vfdata.manifest import load_manifest
from vfdata.recon.segment import mask_iou
from vfdata.recording import Recording
from vfdata.rig import rig_for


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def true_mask(raw: Path, i: int) -> np.ndarray:
    return cv2.imread(str(raw / "ground_truth" / "mask" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE) > 127


def _taper_strength(diagnostics: dict) -> float:
    """The taper cue's strength in the end decision (>= 3 decides alone; vfdata.recon.clamped_end)."""
    return diagnostics.get("end", {}).get("cues", {}).get("taper", {}).get("strength", float("nan"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("manifest", type=Path)
    parser.add_argument("--save-masks", type=Path, help="write first-frame mask pictures here")
    parser.add_argument("--json", type=Path, help="write each recording's figures here")
    args = parser.parse_args()
    rows = []
    for e in load_manifest(args.manifest).entries:
        if not e.mcap.is_file():
            convert_raw_folder(e.raw, e.mcap)
        rec = Recording.open(e.mcap)
        rig = rig_for(rec, e.mcap)
        engine = rig.engine(EngineOptions(tracker="none", object_frame="tissue"), rig.prompt(None),
                            look_ahead=rec.num_frames)
        first = rec.rectified_frame(0)
        images = engine.image_stages(first.left, first.right, first=True)
        engine.track(0, first.stamp_ns, first.left, images)
        truth = json.loads((e.raw / "ground_truth" / "object_frame.json").read_text())
        z_true, o_true = np.array(truth["rotation"])[:, 2], np.array(truth["origin_mm"])
        gt = true_mask(e.raw, 0)
        iou = mask_iou(images.mask, gt)
        z_err = angle_deg(engine.frame.z_axis, z_true)
        origin = float(np.linalg.norm(engine.frame.origin - o_true))
        into_depth = angle_deg(z_true, np.array([0.0, 0.0, 1.0]))
        d = engine.frame.diagnostics
        z_first, tissue = z_err, (droop_figures(e.raw, engine.frame.z_axis)["tissue_err_deg"], None)
        if d.get("rest"):  # the first frame's fit alone (kept in the diagnostics), turned to the frame's end
            direction = np.asarray(d["rest"]["first"])
            direction = direction if direction @ engine.frame.z_axis >= 0 else -direction
            z_first = angle_deg(direction, z_true)
            tissue = (tissue[0], droop_figures(e.raw, direction)["tissue_err_deg"])
        rows.append((e.id, e.orientation_deg, e.split, iou, z_err, origin, 90 - into_depth, d, z_first, tissue))
        print(f"{e.id} {e.orientation_deg:5.0f} {e.split:>5}  IoU {iou:.3f}  Z {z_err:6.1f} deg  origin {origin:6.1f}"
              f"  into depth {90 - into_depth:5.1f} deg  slope {d.get('size_slope', float('nan')):+.3f}"
              f"  check {d.get('axis_check_deg', float('nan')):5.1f} {d.get('axis_from', '')}"
              f"  doubts {','.join(d.get('doubtful', [])) or '-'}"
              f"  taper {_taper_strength(d):.2f}  rest {len(d.get('rest', {}).get('frames', []))}"
              f"  first alone {z_first:5.1f}", flush=True)
        if args.save_masks:
            args.save_masks.mkdir(parents=True, exist_ok=True)
            pic = first.left.copy()
            pic[images.mask & ~gt] = (0, 0, 255)
            pic[~images.mask & gt] = (255, 0, 0)
            pic[images.mask & gt] = (pic[images.mask & gt] * 0.5 + np.array([0, 127, 0])).astype(np.uint8)
            cv2.imwrite(str(args.save_masks / f"{e.id}.png"), pic)
    ious = np.array([r[3] for r in rows])
    z = np.array([r[4] for r in rows])
    first = np.array([r[8] for r in rows])
    print(f"\n{len(rows)} recordings: IoU median {np.median(ious):.3f} min {ious.min():.3f}; "
          f"Z within 10 deg {np.mean(z <= 10):.1%} (first frame alone {np.mean(first <= 10):.1%}), median "
          f"{np.median(z):.2f} ({np.median(first):.2f}) deg, reversed (>90) {int((z > 90).sum())}; "
          f"{sum(bool(r[7].get('rest')) for r in rows)} looked again at rest")
    rested = [r for r in rows if r[9][1] is not None]
    if rested:
        t, t1 = np.array([r[9][0] for r in rested]), np.array([r[9][1] for r in rested])
        print(f"against the tissue's own axis, those {len(rested)}: within 10 deg {np.mean(t <= 10):.1%} (first frame "
              f"alone {np.mean(t1 <= 10):.1%}), median {np.median(t):.2f} ({np.median(t1):.2f}) deg")
    if args.json:
        args.json.write_text(json.dumps([{"id": r[0], "view": r[1], "split": r[2], "iou": r[3], "z_err": r[4],
                                          "z_first": r[8], "tissue": r[9][0], "tissue_first": r[9][1],
                                          "doubtful": r[7].get("doubtful", []), "rest": r[7].get("rest")}
                                         for r in rows], indent=1))


if __name__ == "__main__":
    main()
