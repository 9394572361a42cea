"""`vfdata convert SRC OUT.mcap`: a raw recording folder (or a ROS bag) to a recording MCAP."""

from __future__ import annotations

import argparse
from pathlib import Path

from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("convert", help="convert a raw recording folder to a recording MCAP",
                       description="Convert a raw recording folder (docs/raw_layout.md) to an MCAP file "
                                   "of the VisionForce layout (docs/format.md).")
    p.add_argument("src", type=Path, help="raw recording folder")
    p.add_argument("out", type=Path, help="output .mcap file")
    p.add_argument("--format", dest="image_format", choices=["jpeg", "png"], default="jpeg",
                   help="image compression in the MCAP (default jpeg)")
    p.add_argument("--quality", type=int, default=95, help="JPEG quality 1-100 (default 95)")
    p.add_argument("--force-gap-ms", type=float, default=50.0,
                   help="largest gap allowed in the force stream over the video span (default 50 ms)")
    p.add_argument("--workers", type=int, default=2, help="image encoding threads (default 2)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    options = ConvertOptions(
        image_format=args.image_format, jpeg_quality=args.quality,
        force_gap_tolerance_ns=int(args.force_gap_ms * 1e6), workers=args.workers, progress=not args.quiet,
    )
    out = convert_raw_folder(args.src, args.out, overwrite=args.overwrite, options=options)
    print(f"wrote {out}")
    return 0
