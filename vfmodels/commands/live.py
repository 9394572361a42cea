"""`vfdata live SOURCE --ckpt CKPT`: the streaming estimator on a live source, served to Foxglove over
its WebSocket protocol (docs/live.md).

The heavy modules (torch, the models, foxglove) are imported inside `run`, so `vfdata --help` starts
fast."""

from __future__ import annotations

import argparse
import sys
import threading
from pathlib import Path

from vfdata.commands.engine_flags import add_engine_flags
from vfdata.device import DEVICE_HELP, resolve_device
from vfdata.errors import InputError
from vfdata.recording import layout
from vfdata.threads import set_threads
from vfmodels.commands.predict import model_engine_settings


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "live", help="estimate forces live and serve them to Foxglove (WebSocket), optionally recording them",
        description="Runs the streaming estimator on SOURCE and serves the left image, tissue mask, tracked points, "
                    "tissue cloud, the object frame (/tf) and /force/estimate over the Foxglove WebSocket protocol, "
                    "with the topics and ROS 2 schemas of the files. SOURCE is a recording MCAP (stereo or RGB-D, "
                    "replayed at its own rate) or an OpenCV video source (device index, file or stream URL) with "
                    "--right or --side-by-side and --calibration. Needs the 'live' extra (foxglove-sdk). Ctrl-C stops "
                    "it cleanly (the --record file is then written).")
    p.add_argument("source", help="recording .mcap, or the left (or side-by-side) video source: device index, "
                                  "video file or stream URL")
    p.add_argument("--ckpt", type=Path, required=True,
                   help="trained checkpoint: a .ckpt file, or a run folder (its best checkpoint)")
    p.add_argument("--right", help="the right video source (a pair of OpenCV sources)")
    p.add_argument("--side-by-side", action="store_true", help="SOURCE holds both views side by side")
    p.add_argument("--calibration", type=Path, help="stereo calibration (OpenCV yaml, docs/raw_layout.md) of a "
                                                    "video source")
    p.add_argument("--prompt", help="first-frame tissue prompt, e.g. box:x0,y0,x1,y1 (a recording: default its "
                                    "metadata's prompt_box)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1; 0.0.0.0: all)")
    p.add_argument("--port", type=int, default=8765, help="WebSocket port (default 8765, Foxglove's; 0: any free)")
    p.add_argument("--record", type=Path, help="also write what is served to this MCAP (atomically, at the end)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --record file")
    p.add_argument("--speed", type=float, default=1.0,
                   help="replay speed of a recording (default 1: its own rate; 0: as fast as it runs)")
    p.add_argument("--like-camera", action="store_true",
                   help="replay a recording as a camera delivers: frames the estimator has no time for are "
                        "skipped (default: every frame, late if need be)")
    p.add_argument("--wait-for-client", type=float, default=0.0, metavar="SECONDS",
                   help="wait up to SECONDS for a client to subscribe to /force/estimate before starting")
    p.add_argument("--max-frames", type=int, help="stop after N frames")
    p.add_argument("--depth-roi-margin", type=int, default=None, metavar="PX",
                   help="depth only in the previous frame's tissue box grown by PX pixels (default 24; 0: the "
                        "whole image, as offline processing)")
    p.add_argument("--window", type=int, help="LSTM history in frames (default: the clip length the model was "
                                             "trained on, 16 in every config); 0 carries the state forever")
    p.add_argument("--pipelined", action="store_true",
                   help="image stages of the next frame in a second thread (2 cores; one more frame of delay)")
    add_engine_flags(p, tracker_default=None, device_help=DEVICE_HELP,
                     tracker_help="point tracker (default: the one whose tracks the model was trained on, saved in "
                                  "the checkpoint)")
    p.add_argument("--quiet", action="store_true", help="no summary line")
    p.set_defaults(func=run)


def open_source(args: argparse.Namespace):
    """(source, prompt) for the command's arguments; the source's rig (`source.rig`) knows the rest."""
    # here, not at the top: sources and prompts pull in OpenCV; `vfdata --help` starts without it
    from vfdata.recon import Prompt
    from vfdata.sources import RecordingReplay, VideoStereo

    if args.source.endswith(".mcap"):
        if args.right or args.side_by_side or args.calibration:
            raise InputError(Path(args.source), "a recording carries its own views and calibration: "
                                                "--right, --side-by-side and --calibration are for video sources")
        source = RecordingReplay(args.source, speed=args.speed, max_frames=args.max_frames,
                                 like_camera=args.like_camera)
        try:
            prompt = source.rig.prompt(args.prompt)
        except BaseException:
            source.close()
            raise
        return source, prompt
    if args.calibration is None:
        raise InputError(Path(args.source), "a video source needs --calibration (the stereo calibration yaml)")
    if not args.prompt:
        raise InputError(Path(args.source), "a video source needs --prompt box:x0,y0,x1,y1 (the tissue in the "
                                            "first frame)")
    prompt = Prompt.parse(args.prompt)
    return VideoStereo(args.source, args.right, args.calibration, args.side_by_side, args.max_frames), prompt


def run(args: argparse.Namespace, stop: threading.Event | None = None, ready=None) -> int:
    """`ready(server)`, when given, is called once the server listens (tests use it to connect)."""
    # here, not at the top: torch, the models and foxglove; `vfdata --help` starts without them
    from vfdata.engine import EngineOptions
    from vfdata.foxglove_server import FoxgloveServer, import_foxglove
    from vfmodels.inference.live import LIVE_DEPTH_ROI_MARGIN_PX, StreamingForceEstimator
    from vfmodels.inference.live_session import LiveSession
    from vfmodels.inference.trained_model import TrainedModel

    import_foxglove()  # the missing extra is said before anything else is opened
    device = resolve_device(args.device, "frames")  # the tracker and the model, one frame at a time

    model = TrainedModel.load(args.ckpt, device)
    settings = model_engine_settings(args, model, device)  # tracked as the training recordings were
    set_threads(args.threads)
    roi = LIVE_DEPTH_ROI_MARGIN_PX if args.depth_roi_margin is None else args.depth_roi_margin
    source, prompt = open_source(args)
    server = None
    try:
        # with the stage defaults of the source's kind, as `vfdata process` takes them (RGB-D: the sensor's depth,
        # the board's plane and frame; `vfdata.rig`)
        options = EngineOptions(**settings, depth_roi_margin_px=roi)
        estimator = StreamingForceEstimator(model, source.rig, prompt, options, window=args.window,
                                            pipelined=args.pipelined)
        server = FoxgloveServer(args.host, args.port, record=args.record, overwrite=args.overwrite)
        print(f"serving on {server.url()} (Foxglove: Open connection, Foxglove WebSocket)", file=sys.stderr,
              flush=True)
        if ready is not None:
            ready(server)
        if args.wait_for_client > 0 and not server.wait_for_subscriber(layout.FORCE_ESTIMATE, args.wait_for_client):
            print(f"no client subscribed to {layout.FORCE_ESTIMATE} within {args.wait_for_client:g} s: starting",
                  file=sys.stderr)
        session = LiveSession(source, estimator, server, stop)
        try:
            stats = session.run()
        except KeyboardInterrupt:  # Ctrl-C ends a live session normally: what was served is kept
            stats = session.stats
        estimator.close()
        recorded = server.close(session.metadata())
        server = None
    finally:
        if server is not None:
            server.abort()
        source.close()
    if not args.quiet:
        summary = stats.summary()
        print(f"{summary['frames']} frames, {summary['estimates']} forces at {summary['rate_fps']:.1f} frames/s; "
              f"latency median {summary['latency_median_ms']:.1f} ms, p95 {summary['latency_p95_ms']:.1f} ms "
              f"(from the arrival of the frame each force waited for); {summary['dropped']} frames dropped")
        if summary["unfamiliar"]:
            print(f"warning: {summary['unfamiliar']} of {summary['estimates']} forces came from input unlike any "
                  "training frame (their band is widened)", file=sys.stderr)
        if recorded is not None:
            print(f"wrote {recorded}")
    return 0
