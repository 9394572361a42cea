"""End-to-end rate of the whole pipeline (stereo frames in, force out), per stage and in total.

    python bench/bench_pipeline.py [--recording REC.mcap] [--ckpt CKPT] [--frames 120] [--threads 2]

Feeds the frames of a recording one by one to `vfmodels.inference.live.StreamingForceEstimator` (depth, tissue
mask, tissue cloud, geometry tracking, point tokens + Set Transformer + LSTM) and prints ms/frame and
frames/s per stage, the end-to-end rate and the per-frame latency (median, p95). Decoding the
compressed images stands in for the camera driver and is timed separately, not in the total.
Target (issue 7): >= 10 frames/s end to end on 2 CPU cores.

Then the live session of `vfdata live` (issue 23): the recording replayed at its own rate through the
estimator to the Foxglove server with a client subscribed to /force/estimate, with the live default
(`LIVE_DEPTH_ROI_MARGIN_PX`), serial and pipelined: the rate forces reach the client and the latency
from the arrival of the frame each force waited for to its sending (median, p95); beside it the
offline rate (`vfmodels.inference.predict.predict_recording` on the same frames, no video). Target (issue 23):
30 frames/s on 2 cores, median latency <= 70 ms, p95 <= 100 ms.

Without --recording a short `mini` recording is simulated and converted into --workdir. Without
--ckpt a freshly initialised proposed model is used: its cost does not depend on its weights.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def simulated_recording(workdir: Path, frames: int) -> Path:
    from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder
    from vfdata.sim import synthesize

    # A workdir left by an earlier run (perhaps with another --frames) is replaced, not trusted.
    manifest = synthesize("mini", workdir, seed=0, workers=1, progress=False, frames=frames, overwrite=True)
    raw = manifest.parent / "mini_002"  # the test recording (90 degrees)
    out = workdir / "mini_002.mcap"
    convert_raw_folder(raw, out, overwrite=True, options=ConvertOptions(progress=False))
    return out


def untrained_checkpoint(path: Path) -> Path:
    from vfmodels import ForceRegressor, SetTransformerLSTM

    torch.manual_seed(0)
    reg = ForceRegressor(SetTransformerLSTM(in_features=6))
    reg.set_normalisation(torch.zeros(6), torch.ones(6), torch.zeros(3), torch.ones(3))
    checkpoint = {"state_dict": reg.state_dict(), "hyper_parameters": dict(reg.hparams)}
    reg.on_save_checkpoint(checkpoint)
    torch.save(checkpoint, path)
    return path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--recording", type=Path, help="recording MCAP (default: simulate one)")
    parser.add_argument("--ckpt", type=Path, help="trained checkpoint (default: untrained proposed model)")
    parser.add_argument("--frames", type=int, default=120, help="frames to stream (default 120)")
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch / OpenCV threads (default 1: one per process is fastest here)",
    )
    parser.add_argument("--window", type=int, help="LSTM window (default: the clip length; 0: carried state)")
    parser.add_argument("--depth", default="sgbm")
    parser.add_argument("--segment", default="colortrack")
    parser.add_argument("--depth-roi-margin", type=int, default=24,
                        help="depth region of interest of the streaming runs, px (default 24: the live default; "
                             "0: whole image)")
    parser.add_argument("--no-live", action="store_true", help="skip the live session and the offline rate")
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "vf_bench_pipeline")
    args = parser.parse_args()

    import cv2

    from vfdata.engine import EngineOptions
    from vfdata.recording import Recording
    from vfdata.rig import StereoRig, camera_up, recording_prompt
    from vfmodels.inference.live import StreamingForceEstimator

    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    args.workdir.mkdir(parents=True, exist_ok=True)
    recording = args.recording or simulated_recording(args.workdir, max(args.frames, 30))
    ckpt = args.ckpt or untrained_checkpoint(args.workdir / "untrained.ckpt")

    with Recording.open(recording) as rec:
        prompt = recording_prompt(rec, recording, None)
        n = min(args.frames, rec.num_frames)
        started = time.perf_counter()
        frames = [rec.rectified_frame(i) for i in range(n)]
        decode_ms = 1000.0 * (time.perf_counter() - started) / n
        camera, baseline_mm, up = rec.camera, rec.stereo.baseline_mm, camera_up(rec)

    def stream(pipelined: bool):
        estimator = StreamingForceEstimator(
            ckpt,
            StereoRig(recording, camera=camera, baseline_mm=baseline_mm, up=up),
            prompt,
            EngineOptions(depth=args.depth, segment=args.segment, depth_roi_margin_px=args.depth_roi_margin),
            pipelined=pipelined,
            window=args.window,
        )
        warm = 3  # the first frames fix the object frame and the tracked points: not steady state
        for frame in frames[:warm]:
            estimator.push(frame.left, frame.right, frame.stamp_ns)
        wall0, cpu0 = dict(estimator.stage_seconds), dict(estimator.stage_cpu_seconds)
        latencies = []
        started = time.perf_counter()
        for frame in frames[warm:]:
            t = time.perf_counter()
            estimator.push(frame.left, frame.right, frame.stamp_ns)
            latencies.append(time.perf_counter() - t)
        total = time.perf_counter() - started
        estimator.flush()
        estimator.close()
        count = len(frames) - warm
        wall = {k: 1000.0 * (v - wall0.get(k, 0.0)) / count for k, v in estimator.stage_seconds.items()}
        cpu = {k: 1000.0 * (v - cpu0.get(k, 0.0)) / count for k, v in estimator.stage_cpu_seconds.items()}
        return wall, cpu, 1000.0 * np.array(latencies), count / total

    load = os.getloadavg()[0]
    print(
        f"recording {recording} ({camera.width}x{camera.height}), {n} frames, {args.threads} thread(s) per "
        f"stage, {os.cpu_count()} CPU(s), load average {load:.1f}, torch {torch.__version__}, depth region of "
        f"interest {args.depth_roi_margin} px"
    )
    print(
        "CPU ms: CPU time of the thread that ran the stage (= wall time on an idle core); wall ms also "
        "counts waiting for a CPU when other processes run"
    )
    wall, cpu, latency_ms, serial_fps = stream(pipelined=False)
    print(f"{'stage':<18}{'CPU ms':>9}{'frames/s':>10}{'wall ms':>10}{'frames/s':>10}")
    stages = [s for s in ("depth", "mask", "cloud", "tracking", "force") if s in wall]
    for stage in stages:
        print(
            f"{stage:<18}{cpu[stage]:>9.2f}{1000.0 / cpu[stage]:>10.1f}{wall[stage]:>10.2f}"
            f"{1000.0 / wall[stage]:>10.1f}"
        )
    cpu_total = sum(cpu[s] for s in stages)
    print(
        f"{'end to end, serial':<18}{cpu_total:>9.2f}{1000.0 / cpu_total:>10.1f}{1000.0 / serial_fps:>10.2f}"
        f"{serial_fps:>10.1f}"
    )
    print(f"{'(decode, not in)':<18}{'':>9}{'':>10}{decode_ms:>10.2f}{1000.0 / decode_ms:>10.1f}")
    print(
        f"serial latency per frame: median {np.median(latency_ms):.1f} ms, p95 {np.percentile(latency_ms, 95):.1f} "
        "ms wall (+ one frame period: a frame's force needs the next frame's points for its velocity)"
    )

    image_cpu = sum(cpu[s] for s in ("depth", "mask", "cloud") if s in cpu)
    track_cpu = sum(cpu[s] for s in ("tracking", "force") if s in cpu)
    print(
        f"pipelined on 2 cores, from CPU time: image stages {image_cpu:.1f} ms || tracking + model "
        f"{track_cpu:.1f} ms -> {1000.0 / max(image_cpu, track_cpu):.1f} frames/s on two idle cores "
        "(target >= 10 frames/s)"
    )
    wall_p, cpu_p, latency_p, pipelined_fps = stream(pipelined=True)
    print(
        f"pipelined, measured: {pipelined_fps:.1f} frames/s wall (load average {os.getloadavg()[0]:.1f}), push "
        f"median {np.median(latency_p):.1f} ms; CPU ms per frame "
        + ", ".join(f"{k} {v:.1f}" for k, v in cpu_p.items())
    )
    if not args.no_live:
        live_and_offline(recording, ckpt, n, args)
    return 0


def live_and_offline(recording: Path, ckpt: Path, frames: int, args) -> None:
    import asyncio
    import threading

    from vfdata.engine import EngineOptions
    from vfdata.foxglove_server import FoxgloveServer
    from vfdata.processing import ProcessOptions
    from vfdata.recording import layout
    from vfdata.sources import RecordingReplay
    from vfmodels.inference.live import StreamingForceEstimator
    from vfmodels.inference.live_session import LiveSession
    from vfmodels.inference.predict import predict_recording

    def client(url: str, received: list) -> None:
        import json

        import websockets

        async def run():
            async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"]) as ws:
                async for message in ws:
                    if isinstance(message, str):
                        op = json.loads(message)
                        if op["op"] == "advertise":
                            ids = [c["id"] for c in op["channels"] if c["topic"] == layout.FORCE_ESTIMATE]
                            await ws.send(json.dumps({"op": "subscribe",
                                                      "subscriptions": [{"id": 1, "channelId": ids[0]}]}))
                    else:
                        received.append(time.perf_counter())

        asyncio.run(run())

    print(f"\nlive session (vfdata live): {frames} frames replayed at their own rate, depth region of interest "
          f"{args.depth_roi_margin} px, a client subscribed to {layout.FORCE_ESTIMATE}")
    for pipelined, like_camera in ((False, False), (True, False), (False, True), (True, True)):
        source = RecordingReplay(recording, speed=1.0, max_frames=frames, like_camera=like_camera)
        estimator = StreamingForceEstimator(
            ckpt, source.rig, source.rig.prompt(None),
            EngineOptions(depth=args.depth, segment=args.segment, depth_roi_margin_px=args.depth_roi_margin),
            pipelined=pipelined, window=args.window)
        server = FoxgloveServer(port=0)
        received: list[float] = []
        thread = threading.Thread(target=client, args=(server.url(), received), daemon=True)
        thread.start()
        server.wait_for_subscriber(layout.FORCE_ESTIMATE, 10.0)
        stats = LiveSession(source, estimator, server).run()
        estimator.close()
        server.close()
        source.close()
        thread.join(timeout=5)
        latency = np.array(stats.latency_ms[3:])  # the first frames fix the object frame and the points
        span_s = (stats.forces[-1][0] - stats.forces[0][0]) / 1e9
        mode = ("pipelined" if pipelined else "serial") + (", like a camera" if like_camera else ", every frame")
        print(f"  {mode:26s}: {stats.estimates} forces ({len(received)} received, {stats.dropped} frames skipped) "
              f"at {stats.rate_fps:.1f} frames/s (the recording's {(len(stats.forces) - 1) / span_s:.1f}); "
              f"latency median {np.median(latency):.1f} ms, p95 {np.percentile(latency, 95):.1f} ms "
              f"(load average {os.getloadavg()[0]:.1f})")
    out = args.workdir / "offline"
    started = time.perf_counter()
    result = predict_recording(recording, ckpt, out, ProcessOptions(depth=args.depth, segment=args.segment,
                                                                    max_frames=frames),
                               video=False, progress=False, overwrite=True, reuse_processed=False)
    offline = time.perf_counter() - started
    print(f"  offline  : vfdata predict on the same {result.frames} frames (whole-image depth, no video): "
          f"{result.frames / offline:.1f} frames/s wall")


if __name__ == "__main__":
    sys.exit(main())
