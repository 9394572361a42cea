"""`vfdata predict RECORDING.mcap --ckpt CKPT`: forces from video alone (no force sensor, no ECM pose),
written as /force/estimate with a plot and an overlay video; `--stream` runs frame by frame.

The heavy modules (torch, the models) are imported inside `run`, so `vfdata --help` starts fast."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from vfdata.commands.engine_flags import add_engine_flags, engine_settings
from vfdata.device import DEVICE_HELP, resolve_device
from vfdata.threads import set_threads

if TYPE_CHECKING:
    from vfmodels.inference.trained_model import TrainedModel


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "predict", help="estimate forces on a recording without a force sensor (overlay video, plot, MCAP)",
        description="Processes the recording (depth, tissue mask, object frame, tracks), runs the trained "
                    "point model and writes OUT/<id>.force.mcap (/force/estimate, WrenchStamped in the object "
                    "frame 'tissue_object'; beside it /force/estimate/band, the half-width of each component's "
                    "calibrated 90% band, and /force/estimate/beyond, how far it lies beyond the training range), "
                    "OUT/<id>.force.png and OUT/<id>.overlay.mp4; existing outputs are "
                    "kept unless --overwrite. Without an ECM pose the object frame's X axis is arbitrary (the "
                    "image's up direction made perpendicular to the tissue axis); on an RGB-D recording the frame is "
                    "the board's (Z its normal, X the image's right). The output says which. --stream feeds the "
                    "frames one by one to the live estimator instead and reports its per-frame latency.")
    p.add_argument("recording", type=Path, help="recording MCAP (stereo or RGB-D; force and ECM pose optional)")
    p.add_argument("--ckpt", type=Path, required=True,
                   help="trained checkpoint: a .ckpt file, or a run folder (its best checkpoint)")
    p.add_argument("--prompt", help="first-frame tissue prompt, e.g. box:x0,y0,x1,y1 "
                                    "(default: prompt_box of the recording's metadata)")
    p.add_argument("--out", type=Path, help="output folder (default: beside the recording)")
    p.add_argument("--window", type=int, help="LSTM history in frames (default: the clip length the model was "
                                             "trained on, 16 in every config); 0 carries the state forever")
    p.add_argument("--max-frames", type=int, help="only the first N frames")
    p.add_argument("--no-video", action="store_true", help="skip the overlay video")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument("--stream", action="store_true", help="run the live, frame-by-frame estimator")
    p.add_argument("--pipelined", action="store_true",
                   help="with --stream: image stages of the next frame in a second thread (2 cores)")
    add_engine_flags(p, tracker_default=None, device_help=DEVICE_HELP,
                     tracker_help="point tracker (default: the one whose tracks the model was trained on, saved in "
                                  "the checkpoint; geometry for a checkpoint that does not say)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def model_engine_settings(args: argparse.Namespace, model: TrainedModel, device: str) -> dict:
    """The pipeline flags' EngineOptions fields, the tracker (and its options under the given ones) taken
    from the model unless --tracker names one: the tracks the model was trained on (predict and live)."""
    tracker, tracker_options = model.tracker_settings(device, args.tracker)
    settings = {**engine_settings(args), "tracker": tracker}
    settings["tracker_options"] = {**tracker_options, **settings["tracker_options"]}
    return settings


def run(args: argparse.Namespace) -> int:
    set_threads(args.threads)  # with --pipelined two stages run at once: one thread each (vfdata.threads)
    # here, not at the top: the engine and the models pull in torch; `vfdata --help` starts without it
    from vfmodels.inference.trained_model import TrainedModel

    # the tracker and a stream's model go frame by frame; offline, the model runs over the whole recording
    tracker_device = resolve_device(args.device, "frames")
    device = resolve_device(args.device, "frames" if args.stream else "recording")
    model = TrainedModel.load(args.ckpt, device)
    settings = model_engine_settings(args, model, tracker_device)
    if args.stream:
        return _stream(args, model, settings)
    from vfdata.processing import ProcessOptions  # torch, as above
    from vfmodels.inference.predict import predict_recording

    options = ProcessOptions(**settings, prompt=args.prompt, max_frames=args.max_frames, threads=args.threads)
    result = predict_recording(args.recording, model, args.out, options, window=args.window,
                               video=not args.no_video, progress=not args.quiet, overwrite=args.overwrite)
    print(f"{result.frames} frames; object frame X axis: {result.x_axis}")
    if result.confidence is not None and result.confidence.doubtful:
        print(f"warning: {args.recording}: doubtful: {result.confidence.describe()}", file=sys.stderr)
    if result.metrics is not None:
        m = result.metrics
        print(f"RMSE against the recording's force sensor: {m['rmse']:.3f} N (Fx {m['rmse_fx']:.3f}, Fy "
              f"{m['rmse_fy']:.3f}, Fz {m['rmse_fz']:.3f}; the average of the three, as Table I)")
    print(f"band: {result.band}")
    if result.band_metrics is not None:
        b = result.band_metrics
        print("band against the force sensor: coverage " + ", ".join(
            f"{c} {b['coverage_' + c.lower()]:.0%} (+-{b['half_width_' + c.lower()]:.2f} N)"
            for c in ("Fx", "Fy", "Fz")))
    say_marks(result.frames_beyond, result.frames_unfamiliar, result.frames)
    stages = {**result.stage_fps, "force": result.force_fps}
    print("frames/s per stage: " + ", ".join(f"{k} {v:.1f}" for k, v in stages.items()))
    for path in (result.force_mcap, result.plot, result.video):
        if path is not None:
            print(f"wrote {path}")
    return 0


def _stream(args: argparse.Namespace, model: TrainedModel, settings: dict) -> int:
    from vfdata.engine import EngineOptions  # torch: here, not at the top (see run)
    from vfmodels.inference.stream import stream_recording

    result = stream_recording(args.recording, model, args.out, EngineOptions(**settings), prompt=args.prompt,
                              window=args.window, pipelined=args.pipelined, max_frames=args.max_frames,
                              overwrite=args.overwrite, progress=not args.quiet)
    if result.confidence.doubtful:
        print(f"warning: {args.recording}: doubtful: {result.confidence.describe()}", file=sys.stderr)
    latency_ms, delay = result.latency_ms, 2 if args.pipelined else 1
    print(f"{result.estimates} estimates from {result.frames} frames; per-frame latency (push) median "
          f"{np.median(latency_ms):.1f} ms, p95 {np.percentile(latency_ms, 95):.1f} ms, "
          f"{1000.0 / np.mean(latency_ms):.1f} frames/s (+ {delay} frame(s) of delay: the central-difference "
          "velocity needs the next frame" + (", and the pipeline one more" if args.pipelined else "") + ")")
    print("ms/frame per stage, wall: " + ", ".join(f"{k} {v:.1f}" for k, v in result.stage_ms.items()))
    print("ms/frame per stage, CPU of its thread (= wall on an idle core): "
          + ", ".join(f"{k} {v:.1f}" for k, v in result.stage_cpu_ms.items())
          + f"; sum {sum(result.stage_cpu_ms.values()):.1f} (includes the first frame's set-up)")
    say_marks(result.frames_beyond, result.frames_unfamiliar, result.estimates)
    print(f"wrote {result.force_mcap}")
    return 0


def say_marks(beyond: int, unfamiliar: int, frames: int) -> None:
    """The warnings on estimates the band cannot speak for, offline and streamed alike."""
    if beyond:
        print(f"warning: {beyond} of {frames} frames have a force beyond the training range "
              f"(marked on /force/estimate/beyond and in the plot): no band speaks for them")
    if unfamiliar:
        print(f"warning: {unfamiliar} of {frames} frames look unlike any training frame (the model's input, farther "
              f"from training than 99% of validation's; marked on /force/estimate/unlike and in the plot): their "
              f"band is widened, and such frames erred twice as much on unseen views")
