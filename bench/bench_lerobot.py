"""LeRobot out and back (docs/lerobot.md, "Figures"): the simulator's mini dataset exported with
`vfdata export --lerobot` and converted back with `vfdata convert`, per video codec setting: export and
import rates, video size per frame, the image loss (PSNR of every left frame, colour and luma, against
the recording's own frames), whether stamps and forces come back exactly; with `--experiment`, for
the original recordings and each round trip, the KLT tracks `vfdata experiment` makes scored against
the simulator's ground truth (what the codec's loss costs the tracking) and the ridge variant's test
RMSE (which on mini moves with any change of the images; docs/experiments.md).

    python bench/bench_lerobot.py [--frames N] [--experiment] [--work DIR]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from vfdata.cli import main as vfdata  # noqa: E402
from vfdata.conversion.lerobot_dataset import convert_lerobot_dataset  # noqa: E402
from vfdata.conversion.options import ConvertOptions  # noqa: E402
from vfdata.conversion.raw_folder import convert_raw_folder  # noqa: E402
from vfdata.lerobot.export import ExportOptions, export_lerobot  # noqa: E402
from vfdata.lerobot.video import psnr_db  # noqa: E402
from vfdata.manifest import load_manifest  # noqa: E402
from vfdata.recording import Recording  # noqa: E402
from vfdata.sim.synthesize import synthesize  # noqa: E402

SETTINGS = [("av1", 20, "default"), ("av1", 30, "LeRobot's default crf"), ("av1", 10, ""), ("h264", 18, ""),
            ("h264", 8, "")]


def quiet(fn, *args, **kwargs):
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        return fn(*args, **kwargs)


def compare(original: Path, back: Path) -> dict:
    with Recording.open(original) as a, Recording.open(back) as b:
        colour, luma = [], []
        for i in range(a.num_frames):
            x, y = a.frame(i).left, b.frame(i).left
            colour.append(psnr_db(x, y))
            luma.append(psnr_db(cv2.cvtColor(x, cv2.COLOR_BGR2GRAY), cv2.cvtColor(y, cv2.COLOR_BGR2GRAY)))
        span = (a.force.times_ns > a.frame_times_ns[0] - round(1e9 / 30)) & (a.force.times_ns <= a.frame_times_ns[-1])
        exact = (np.array_equal(a.frame_times_ns, b.frame_times_ns) and np.array_equal(a.force.times_ns[span],
                                                                                        b.force.times_ns)
                 and np.array_equal(a.force.wrench[span], b.force.wrench))
        return {"colour": colour, "luma": luma, "exact": exact, "left_out": int((~span).sum())}


def ridge_and_tracking(manifest: Path, out: Path, ground_truth: Path) -> tuple[float, float, float]:
    """The ridge's test RMSE (N) and the KLT tracks' error against ground truth (median and 95th
    percentile over every tracked point of the recordings, mm; mean over recordings)."""
    import json

    from vfmodels.experiment.report import tracking_quality

    quiet(vfdata, ["experiment", str(manifest), "--out", str(out), "--variants", "ridge", "--seeds", "1"])
    rmse = json.loads((out / "runs" / "ridge" / "seed0" / "metrics.json").read_text())["pooled"]["rmse"]
    errors = []
    for entry in load_manifest(manifest).entries:
        klt = entry.mcap.with_name(f"{entry.id}.klt.mcap")
        errors.append(tracking_quality(klt, entry.mcap, ground_truth / entry.id / "ground_truth")["error"])
    return (rmse, float(np.mean([e["full_median_mm"] for e in errors])),
            float(np.mean([e["full_p95_mm"] for e in errors])))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=None, help="cut each mini recording to N frames")
    parser.add_argument("--experiment", action="store_true", help="also train the ridge on both and compare")
    parser.add_argument("--work", type=Path, default=None, help="working folder (default: a temporary one)")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_lerobot_"))
    mini = work / "mini"
    if not (mini / "mini.manifest.yaml").is_file():
        synthesize("mini", mini, frames=args.frames, progress=False)
    recordings = []
    for raw in sorted(p for p in mini.iterdir() if p.is_dir()):
        out = mini / f"{raw.name}.mcap"
        if not out.is_file():
            convert_raw_folder(raw, out, options=ConvertOptions(progress=False))
        recordings.append(out)
    frames = sum(Recording.open(p).num_frames for p in recordings)
    print(f"mini: {len(recordings)} recordings, {frames} stereo frames of 640x512; work folder {work}")
    print("| video | export frames/s | KB per frame and view | import frames/s | PSNR colour mean / min (dB) "
          "| PSNR luma mean / min (dB) | stamps and forces exact |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | --- |")
    manifests = {"original (JPEG 95)": mini / "mini.manifest.yaml"}
    for codec, crf, note in SETTINGS:
        name = f"{codec}_crf{crf}"
        dataset, back = work / name, work / f"{name}_back"
        started = time.perf_counter()
        export_lerobot(recordings, dataset, overwrite=True, options=ExportOptions(codec=codec, crf=crf, progress=False))
        exported = time.perf_counter() - started
        size = sum(p.stat().st_size for p in (dataset / "videos").rglob("*.mp4")) / 2 / frames / 1024
        started = time.perf_counter()
        manifest = convert_lerobot_dataset(dataset, back, overwrite=True,
                                           options=ConvertOptions(progress=False, image_format="png"))
        imported = time.perf_counter() - started
        found = [compare(p, back / p.name) for p in recordings]
        colour = np.concatenate([f["colour"] for f in found])
        luma = np.concatenate([f["luma"] for f in found])
        exact = all(f["exact"] for f in found)
        label = f"{codec} crf {crf}" + (f" ({note})" if note else "")
        print(f"| {label} | {frames / exported:.0f} | {size:.1f} | {frames / imported:.0f} | "
              f"{colour.mean():.2f} / {colour.min():.2f} | {luma.mean():.2f} / {luma.min():.2f} | {exact} |")
        manifests[label] = manifest
        left_out = sum(f["left_out"] for f in found)
    print(f"force samples outside the video span (before one frame period ahead of the first frame, after the "
          f"last frame), not exported: {left_out}")
    print("(import written as PNG, so that the PSNR is the video codec's alone; the recordings' own frames are "
          "JPEG 95)")
    if args.experiment:
        print()
        print("| images | KLT tracking error median / p95 (mm) | ridge test RMSE (N) |")
        print("| --- | ---: | ---: |")
        for i, (label, manifest) in enumerate(manifests.items()):
            rmse, median, p95 = ridge_and_tracking(manifest, work / f"ridge_{i}", mini)
            print(f"| {label} | {median:.3f} / {p95:.2f} | {rmse:.2f} |")


if __name__ == "__main__":
    main()
