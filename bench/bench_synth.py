"""Generation rate of `vfdata synth` at 640x512. Target: >= 30 stereo frames/s on 2 cores end to end,
i.e. `glove` (16,292 frames) in under 10 minutes.

Three measurements:

0. The one-off cost of the renderer's compiled kernels (numba): CPU time of a fresh process that
   imports the renderer and runs `warm_up()` with an empty cache (compiles) and again (loads from
   the cache), both in a throw-away cache folder (`--jit`; the project's own cache is not touched).

1. A per-stage breakdown in CPU time of this process (physics, rendering, encoding of the stereo
   views, encoding of the ground-truth mask and depth, ground-truth points) on a few recordings
   spread over the preset (their views differ in cost), which depends little on other load on the
   machine; the per-recording costs (scene set-up, the static equilibrium the sensor is tared at)
   apart; the CPU time the whole preset needs from them.
2. End to end: `synthesize(preset, frames=N)` (every recording cut to N frames) with the given
   numbers of worker processes: wall clock and the CPU time of all processes (a busy machine shows
   as wall >> CPU / cores). Cut recordings pay the per-recording costs over fewer frames than the
   preset's, so the CPU time per frame is a little pessimistic.

    python bench/bench_synth.py [--preset glove] [--frames 300] [--recordings 4] [--workers 2] [--image-format jpeg]
                                [--jit]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from vfdata.sim.png import encode_png16  # noqa: E402
from vfdata.sim.presets import get_preset  # noqa: E402
from vfdata.sim.raw_writer import (  # noqa: E402
    IMAGE_FORMATS,
    N_MATERIAL_POINTS,
    PNG_MASK,
    ground_truth_images,
    point_visibility,
)
from vfdata.sim.render import warm_up  # noqa: E402
from vfdata.sim.scene import SceneRenderer  # noqa: E402
from vfdata.sim.simulation import build_recording, simulate  # noqa: E402
from vfdata.sim.synthesize import synthesize  # noqa: E402

TARGET_FPS = 30.0


def breakdown(preset: str, frames: int, image_format: str, recordings: int = 4) -> dict[str, float]:
    """CPU milliseconds per frame of each stage, in this process (one thread), over `recordings`
    recordings spread over the preset (train, validation and test views differ in cost: the tissue's
    and the instrument's sizes in the image), `frames` frames each."""
    cv2.setNumThreads(1)
    suffix, params = IMAGE_FORMATS[image_format]
    p = get_preset(preset)
    picks = sorted(set(np.linspace(0, len(p.recordings) - 1, recordings).round().astype(int).tolist()))
    cost = dict.fromkeys(("render", "views", "gt_images", "gt_points"), 0.0)
    setup = total = 0.0
    for index in picks:
        rec = build_recording(p.recordings[index], seed=0, frames=frames)
        t = time.process_time()
        renderer = SceneRenderer(rec.spec, rec.streams["render"])
        rec.model.relax(tol_n=1e-8)  # as simulate() starts (there it then converges at once)
        setup += time.process_time() - t
        point_map = rec.spec.tube.surface_map(*rec.spec.tube.material_points(N_MATERIAL_POINTS))
        r_co, t_co = rec.spec.object_to_camera()

        def on_frame(i, t_s, grasp, twist, jaw, rec=rec, renderer=renderer, point_map=point_map, r_co=r_co,
                     t_co=t_co):
            t0 = time.process_time()
            f = renderer.render(rec.model.nodes, grasp, twist, jaw)
            t1 = time.process_time()
            cv2.imencode(suffix, f.left, params)
            cv2.imencode(suffix, f.right, params)
            t2 = time.process_time()
            mask, depth = ground_truth_images(f.mask, f.depth_mm)
            cv2.imencode(".png", mask, PNG_MASK)
            encode_png16(depth)
            t3 = time.process_time()
            p, n = point_map.evaluate_scattered(rec.model.nodes)
            point_visibility(rec.spec.cam.camera, p @ r_co.T + t_co, n @ r_co.T, f.depth_mm, f.mask)
            t4 = time.process_time()
            for key, dt in zip(cost, (t1 - t0, t2 - t1, t3 - t2, t4 - t3), strict=True):
                cost[key] += dt

        t = time.process_time()
        simulate(rec, on_frame)
        total += time.process_time() - t
    n_frames = frames * len(picks)
    out = {k + "_ms": v / n_frames * 1e3 for k, v in cost.items()}
    out["physics_ms"] = (total - sum(cost.values())) / n_frames * 1e3
    out["setup_s"] = setup / len(picks)
    out["recordings"] = len(picks)
    # The scene set-up (textures, static layer, equilibrium) is paid once per recording: spread it
    # over the preset's mean recording length.
    out["setup_ms"] = out["setup_s"] / (p.total_frames / len(p.recordings)) * 1e3
    out["total_ms"] = sum(v for k, v in out.items() if k.endswith("_ms"))
    out["preset_cpu_s"] = p.total_frames * out["total_ms"] / 1e3
    return out


_WARM_UP = """
import time
t = time.process_time()
from vfdata.sim.render import warm_up
warm_up()
print(time.process_time() - t)
"""


def jit_cost() -> tuple[float, float]:
    """CPU seconds of a fresh process importing the renderer and running warm_up(): with an empty numba
    cache (compiling every kernel), then with the cache that run left (loading them)."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        runs = [float(subprocess.run([sys.executable, "-c", _WARM_UP], env=env, check=True, capture_output=True,
                                     text=True).stdout.split()[-1]) for _ in range(2)]
    return runs[0], runs[1]


def end_to_end(preset: str, frames: int, workers: int, image_format: str) -> tuple[float, float, int]:
    """(wall s, CPU s of this process and its workers, stereo frames) of `synthesize(preset, frames=...)`."""
    before = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        synthesize(preset, tmp, seed=0, workers=workers, progress=False, frames=frames, image_format=image_format)
        wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = sum(a.ru_utime + a.ru_stime - b.ru_utime - b.ru_stime for a, b in zip(after, before, strict=True))
    return wall, cpu, frames * len(get_preset(preset).recordings)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="glove", choices=["mini", "glove", "colon"])
    ap.add_argument("--frames", type=int, default=300, help="frames per recording")
    ap.add_argument("--recordings", type=int, default=4, help="recordings in the per-stage breakdown")
    ap.add_argument("--workers", type=int, nargs="*", default=[2], help="end-to-end runs (none: skip)")
    ap.add_argument("--image-format", default="jpeg", choices=sorted(IMAGE_FORMATS))
    ap.add_argument("--jit", action="store_true", help="measure compiling the renderer kernels from scratch")
    args = ap.parse_args()
    load0 = os.getloadavg()[0]
    if args.jit:
        cold, warm = jit_cost()
        print(f"renderer kernels in a fresh process (import + warm_up): {cold:.1f} s CPU compiling them (first run on "
              f"a machine), {warm:.2f} s loading them from numba's cache")
    t = time.process_time()
    warm_up()  # (compiled or loaded here: not counted in the first recording's set-up)
    print(f"renderer kernels ready in {time.process_time() - t:.2f} s CPU")
    b = breakdown(args.preset, args.frames, args.image_format, args.recordings)
    print(f"per-frame CPU time ({args.preset}, 640x512, views as {args.image_format}, "
          f"{b['recordings']} recordings x {args.frames} frames):")
    for key, label in (("physics_ms", "physics (2 implicit steps, sensor)"),
                       ("render_ms", "rendering (both views)"),
                       ("views_ms", f"encoding left + right ({args.image_format})"),
                       ("gt_images_ms", "encoding GT mask + depth (PNG)"),
                       ("gt_points_ms", "GT material points + visibility"),
                       ("setup_ms", f"set-up + equilibrium ({b['setup_s']:.2f} s per recording, spread)"),
                       ("total_ms", "total")):
        print(f"  {label:48s} {b[key]:6.1f} ms")
    print(f"CPU-bound rate: {1e3 / b['total_ms']:.1f} stereo frames/s per core, "
          f"{2e3 / b['total_ms']:.1f} on 2 cores (target >= {TARGET_FPS:.0f}: <= {2e3 / TARGET_FPS:.1f} ms per frame)")
    for workers in args.workers:
        wall, cpu, n = end_to_end(args.preset, args.frames, workers, args.image_format)
        print(f"end to end, {args.preset} x {args.frames} frames per recording ({n} frames), {workers} worker(s): "
              f"{n / wall:.1f} stereo frames/s wall, {cpu / n * 1e3:.1f} ms CPU per frame "
              f"(= {2 * n / cpu:.1f} frames/s on 2 idle cores: {'meets' if 2 * n / cpu >= TARGET_FPS else 'short of'} "
              f"the target {TARGET_FPS:.0f})")
    total = get_preset(args.preset).total_frames
    print(f"TARGET: >= {TARGET_FPS:.0f} stereo frames/s on 2 cores. CPU-bound: {args.preset} ({total} frames) needs "
          f"{b['preset_cpu_s'] / 60:.1f} min of CPU = {b['preset_cpu_s'] / 120:.1f} min on 2 idle cores "
          f"(target for glove < 10 min)")
    print(f"load average: {load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end, on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
