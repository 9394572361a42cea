"""Generation rate of `vfdata synth` at 640x512: stereo frames per second end to end (physics,
rendering, PNG writing, ground truth) with 1 and 2 worker processes, and a per-stage breakdown in
CPU time (robust to other load on the machine). Target: >= 30 stereo frames/s on 2 cores.

    python bench/bench_synth.py [--frames 150] [--preset glove]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from vfdata.sim.presets import get_preset  # noqa: E402
from vfdata.sim.scene import SceneRenderer  # noqa: E402
from vfdata.sim.synthesize import _PNG_DEPTH, _PNG_MASK, _PNG_RGB, build_recording, simulate, synthesize  # noqa: E402


def breakdown(preset: str, frames: int) -> dict[str, float]:
    """CPU milliseconds per frame of each stage, in this process."""
    cv2.setNumThreads(1)
    rec = build_recording(get_preset(preset).recordings[0], seed=0, frames=frames)
    t = time.process_time()
    renderer = SceneRenderer(rec.spec, rec.streams["render"])
    setup = time.process_time() - t
    cost = {"render": 0.0, "png": 0.0}

    def on_frame(i, t_s, grasp, twist, jaw):
        t0 = time.process_time()
        f = renderer.render(rec.model.nodes, grasp, twist, jaw)
        t1 = time.process_time()
        cv2.imencode(".png", f.left, _PNG_RGB)
        cv2.imencode(".png", f.right, _PNG_RGB)
        cv2.imencode(".png", f.mask.astype(np.uint8) * 255, _PNG_MASK)
        cv2.imencode(".png", (f.depth_mm * 10).astype(np.uint16), _PNG_DEPTH)
        cost["render"] += t1 - t0
        cost["png"] += time.process_time() - t1

    t = time.process_time()
    simulate(rec, on_frame)
    total = time.process_time() - t
    return {
        "setup_s": setup,
        "physics_ms": (total - cost["render"] - cost["png"]) / frames * 1e3,
        "render_ms": cost["render"] / frames * 1e3,
        "png_ms": cost["png"] / frames * 1e3,
        "total_ms": total / frames * 1e3,
    }


def end_to_end(frames: int, workers: int) -> float:
    """Stereo frames per second (wall clock) of `synthesize('mini', frames=...)`."""
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        synthesize("mini", tmp, seed=0, workers=workers, progress=False, frames=frames)
        wall = time.perf_counter() - t
    return 3 * frames / wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=150, help="frames per recording")
    ap.add_argument("--preset", default="glove", choices=["glove", "colon"], help="tissue for the breakdown")
    args = ap.parse_args()
    b = breakdown(args.preset, args.frames)
    print(
        f"per-frame CPU time ({args.preset}, 640x512): physics {b['physics_ms']:.1f} ms, "
        f"render {b['render_ms']:.1f} ms, PNG {b['png_ms']:.1f} ms, total {b['total_ms']:.1f} ms "
        f"(scene setup {b['setup_s']:.2f} s)"
    )
    print(
        f"CPU-bound rate: {1e3 / b['total_ms']:.1f} stereo frames/s per core, "
        f"{2e3 / b['total_ms']:.1f} on 2 cores (target >= 30)"
    )
    for workers in (1, 2):
        rate = end_to_end(args.frames, workers)
        print(
            f"end to end, mini x {args.frames} frames, {workers} worker(s): {rate:.1f} stereo frames/s (wall)"
        )
    print(f"load average during the run: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
