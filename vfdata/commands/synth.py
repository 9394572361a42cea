"""`vfdata synth`: simulated tissue-manipulation recordings with ground truth (see docs/synthetic.md)."""

from __future__ import annotations

import argparse
import math
import sys

from vfdata.sim.presets import PRESETS


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "synth",
        help="simulate recordings with ground truth (raw folders + dataset manifest)",
        description="Simulate stereo-endoscope recordings of a clamped tissue pulled by a grasper, with "
        "force/torque, ECM pose and ground truth (mask, depth, material points, object frame). Writes "
        "one raw recording folder per recording (the layout `vfdata convert` reads) and "
        "OUT_DIR/<preset>.manifest.yaml.",
    )
    p.add_argument("out_dir", metavar="OUT_DIR", help="folder for the recordings (created if missing)")
    p.add_argument("--preset", required=True, choices=sorted(PRESETS), help="which dataset to make")
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed and version: same bytes)")
    p.add_argument("--workers", type=int, default=1, help="parallel worker processes (default 1)")
    p.add_argument("--frames", type=int, default=None, metavar="N",
                   help="override the number of frames of every recording (quick runs)")
    p.add_argument("--image-format", choices=["jpeg", "png"], default="jpeg",
                   help="stereo views as JPEG quality 95 (default, fast) or lossless PNG; the ground truth "
                   "is always lossless PNG")
    p.add_argument("--test-orientations", type=_orientations, default=None, metavar="DEG[,DEG...]",
                   help="turn the preset's test recordings to these orientations (degrees about the vertical), "
                   "spread over them as evenly as possible, e.g. 90,180 or 60 (default: the preset's)")
    p.add_argument("--train-recordings", type=_count, default=None, metavar="N",
                   help="N training recordings, each its own tissue: the preset's first N, or all of them and new "
                   "ones after the others; validation and test recordings stay the same (default: the preset's; "
                   "colon 5, glove 12)")
    p.add_argument("--val-recordings", type=_count, default=None, metavar="N",
                   help="N validation recordings, each its own tissue, likewise (default: the preset's; colon 1, "
                   "glove 4): the band is calibrated on them")
    p.add_argument("--overwrite", action="store_true",
                   help="replace existing recordings made with other settings")
    p.set_defaults(func=run)


def _orientations(text: str) -> tuple[float, ...]:
    """'90,180' -> (90.0, 180.0); anything else is a usage error naming the option."""
    try:
        angles = tuple(float(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a comma-separated list of degrees (e.g. 90,180)") from None
    if not all(math.isfinite(a) for a in angles):
        raise argparse.ArgumentTypeError(f"'{text}': angles must be finite numbers of degrees")
    return angles


def _count(text: str) -> int:
    """'10' -> 10; anything but a whole number >= 1 is a usage error naming the option."""
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number of recordings >= 1")
    return int(text)


def run(args: argparse.Namespace) -> int:
    # Here, not at the top: it loads the renderer's compiled kernels, which no other command needs.
    from vfdata.sim import synthesize

    path = synthesize(args.preset, args.out_dir, seed=args.seed, workers=args.workers,
                      progress=sys.stderr.isatty(), frames=args.frames, overwrite=args.overwrite,
                      image_format=args.image_format, test_orientations=args.test_orientations,
                      split_recordings={"train": args.train_recordings, "val": args.val_recordings})
    print(path)
    return 0
