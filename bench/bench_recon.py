"""Benchmark of the reconstruction stages (issue 4): speed per stage at 640x512 on two cores, and
accuracy on the real SCARED frame and on the simulator's recordings.

    python bench/bench_recon.py                      # speed + SCARED + accuracy on `mini` (60 frames)
    python bench/bench_recon.py --data data/mini     # accuracy on an existing synthesized preset
    python bench/bench_recon.py --speed-only

Timings are wall-clock per call with OpenCV limited to 2 threads; the minimum over the repetitions is
reported next to the median because the machine may be shared (the minimum is the figure of an
unloaded machine, the median what this run saw). The paper's figures for comparison: depth 1 frame/s
(Stereo Any Video) and SAM2 24 frames/s, both on an RTX A5000.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from vfdata.calibration import StereoCalibration  # noqa: E402
from vfdata.recon import (  # noqa: E402
    Prompt,
    estimate_object_frame,
    make_depth_estimator,
    make_segmenter,
    mask_iou,
    tissue_cloud,
    up_in_camera,
)

PAPER_DEPTH_FPS = 1.0
PAPER_SAM2_FPS = 24.0
SCARED = ROOT.parent / "shared" / "data" / "scared"
# The simulator's working range: tissue at 60-120 mm, instruments from ~50 mm, bed up to ~240 mm
# with fx 560 px and a 4.6 mm baseline -> disparities 10 to 52 px; 8-64 leaves margin on both sides.
SIM_DEPTH_OPTIONS = {"min_disparity": 8, "max_disparity": 64}


CPU_SECONDS: dict[str, float] = {}


def timed(fn, repeats: int, key: str = "") -> tuple[float, float, object]:
    """(min, median) wall seconds of fn() over `repeats` calls after one warm-up, and its result.
    The mean CPU seconds per call (all threads of this process) go to CPU_SECONDS[key]: unlike wall
    time it hardly changes when other processes share the cores."""
    result = fn()
    times = []
    cpu0 = time.process_time()
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    CPU_SECONDS[key] = (time.process_time() - cpu0) / repeats
    return min(times), float(np.median(times)), result


def load_recording(rec: Path, frames: int) -> dict:
    out: dict = {"left": [], "right": [], "mask": [], "depth": []}
    for i in range(frames):
        name = f"{i:06d}.png"
        if not (rec / "left" / name).is_file():
            break
        out["left"].append(cv2.imread(str(rec / "left" / name)))
        out["right"].append(cv2.imread(str(rec / "right" / name)))
        out["mask"].append(cv2.imread(str(rec / "ground_truth" / "mask" / name), 0) > 0)
        depth = cv2.imread(str(rec / "ground_truth" / "depth" / name), cv2.IMREAD_UNCHANGED).astype(
            np.float32
        )
        depth /= 10.0
        depth[depth == 0] = np.nan
        out["depth"].append(depth)
    out["meta"] = yaml.safe_load((rec / "meta.yaml").read_text())
    out["calib"] = StereoCalibration.load(rec / "calibration.yaml").rectified
    out["truth"] = json.loads((rec / "ground_truth" / "object_frame.json").read_text())
    pose = np.loadtxt(rec / "ecm_pose.csv", delimiter=",", skiprows=1, ndmin=2)[0]
    out["up"] = up_in_camera(pose[4:8])
    return out


def synthesize_data(frames: int) -> Path:
    from vfdata.sim import synthesize

    folder = Path(tempfile.gettempdir()) / f"vfdata-bench-recon-mini-{frames}"
    synthesize("mini", folder, seed=0, workers=2, progress=True, frames=frames)
    return folder


def bench_scared() -> None:
    if not (SCARED / "left.png").is_file():
        print(f"SCARED frame not found in {SCARED}: skipped")
        return
    left, right = cv2.imread(str(SCARED / "left.png")), cv2.imread(str(SCARED / "right.png"))
    gt = cv2.imread(str(SCARED / "disparity.tiff"), cv2.IMREAD_UNCHANGED)
    valid = (gt > 0) & (cv2.imread(str(SCARED / "occlusion.png"), cv2.IMREAD_UNCHANGED) != 128)
    print("\nSCARED frame (590x512, disparities 16-86 px), end-point error over all valid pixels:")
    print(f"{'variant':44s} {'EPE px':>7s} {'density':>8s}")
    raw = cv2.StereoSGBM_create(0, 96, 5, P1=8 * 3 * 25, P2=32 * 3 * 25, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    plain = raw.compute(left, right).astype(np.float32) / 16
    ok = valid & (plain > 0)
    print(
        f"{'plain OpenCV SGBM (README reference)':44s} {np.abs(plain - gt)[ok].mean():7.3f} "
        f"{ok.sum() / valid.sum():8.3f}"
    )
    for label, options in [
        ("sgbm: match + guided fill only", {"refine_window": 0, "smooth_radius": 0}),
        ("sgbm: + full-res sub-pixel refinement", {"smooth_radius": 0}),
        ("sgbm default (+ guided-filter smoothing)", {}),
    ]:
        disp = make_depth_estimator("sgbm", **options).disparity(left, right)
        given = valid & np.isfinite(disp) & (disp > 0)
        print(f"{label:44s} {np.abs(disp - gt)[given].mean():7.3f} {given.sum() / valid.sum():8.3f}")
    print("target: EPE <= 0.4 px with density 1.000")


def bench_speed(rec: dict, repeats: int) -> None:
    cv2.setNumThreads(2)
    left, right = rec["left"], rec["right"]
    cam, baseline = rec["calib"].left, rec["calib"].baseline_mm
    h, w = left[0].shape[:2]
    print(f"\nSpeed per stage at {w}x{h}, OpenCV on 2 threads ({repeats} repetitions; min / median):")
    rows = []

    depth_est = make_depth_estimator("sgbm", **SIM_DEPTH_OPTIONS)
    t_min, t_med, depth = timed(lambda: depth_est.depth_mm(left[0], right[0], cam, baseline), repeats, "d64")
    rows.append(("depth (sgbm, 8-64 px)", t_min, t_med, 30.0, PAPER_DEPTH_FPS, "Stereo Any Video", "d64"))
    # Throughput of the overlapped stream (matching of the next pair during this one's refinement).
    pairs = list(zip(left, right, strict=True))
    stream_times = []
    cpu0 = time.process_time()
    for _ in range(3):
        start = time.perf_counter()
        for _depth in depth_est.depth_stream(pairs, cam, baseline):
            pass
        stream_times.append((time.perf_counter() - start) / len(pairs))
    CPU_SECONDS["stream"] = (time.process_time() - cpu0) / (3 * len(pairs))
    rows.append(
        (
            "depth stream (sgbm 8-64, overlapped)",
            min(stream_times),
            float(np.median(stream_times)),
            30.0,
            PAPER_DEPTH_FPS,
            "Stereo Any Video",
            "stream",
        )
    )
    depth_scared = make_depth_estimator("sgbm")
    t_min2, t_med2, _ = timed(lambda: depth_scared.disparity(left[0], right[0]), repeats, "d96")
    rows.append(
        ("depth (sgbm, 0-96 px as SCARED)", t_min2, t_med2, 30.0, PAPER_DEPTH_FPS, "Stereo Any Video", "d96")
    )

    segmenter = make_segmenter("colortrack")
    prompt = Prompt.from_box(rec["meta"]["prompt_box"])
    depths = [depth_est.depth_mm(a, b, cam, baseline) for a, b in zip(left, right, strict=True)]
    segmenter.start(left[0], prompt, depths[0])
    index = [0]

    def track():
        index[0] = index[0] % (len(left) - 1) + 1
        return segmenter.track(left[index[0]], depths[index[0]])

    t_min, t_med, _ = timed(track, max(repeats, len(left) - 1), "mask")
    rows.append(("mask (colortrack, with depth)", t_min, t_med, 30.0, PAPER_SAM2_FPS, "SAM2", "mask"))

    mask = rec["mask"][0]
    for backend in ("numpy", "open3d"):
        try:
            t_min, t_med, points = timed(
                lambda b=backend: tissue_cloud(depth, mask, cam, backend=b), repeats, backend
            )
        except Exception as exc:  # open3d may be missing its system library
            print(f"cloud ({backend}): unavailable: {exc}")
            continue
        rows.append((f"point cloud ({backend})", t_min, t_med, 60.0, None, "", backend))
    points = tissue_cloud(depth, mask, cam)
    cpu0 = time.process_time()
    t_min_of, t_med_of, _ = timed(lambda: estimate_object_frame(points, up=rec["up"]), 3)
    cpu_of = (time.process_time() - cpu0) / 4

    print(f"{'stage':38s} {'ms min':>7s} {'ms med':>7s} {'ms cpu':>7s} {'fps':>7s} {'target':>7s}  vs paper")
    for name, tmin, tmed, target, paper, paper_name, key in rows:
        fps = 1.0 / tmin
        ratio = f"{fps / paper:6.1f}x {paper_name} ({paper:g} fps, RTX A5000)" if paper else ""
        flag = "ok" if fps >= target else "SHORT"
        cpu = CPU_SECONDS.get(key, float("nan")) * 1e3
        print(
            f"{name:38s} {tmin * 1e3:7.1f} {tmed * 1e3:7.1f} {cpu:7.1f} {fps:7.1f} {target:5.0f} {flag:>5s}  {ratio}"
        )
    print("(fps from the minimum wall time; 'ms cpu' is CPU time per frame summed over threads)")
    print(
        f"{'object frame (' + str(len(points)) + ' points)':38s} {t_min_of:6.2f}s {t_med_of:6.2f}s  "
        f"cpu {cpu_of:.2f}s  target <= 2 s per recording {'ok' if t_min_of <= 2 else 'SHORT'}"
    )


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = abs(float(a @ b)) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(min(1.0, cos))))


def bench_accuracy(data: Path, frames: int) -> None:
    recordings = sorted(p.parent for p in data.glob("*/meta.yaml"))
    if not recordings:
        print(f"no recordings in {data}")
        return
    print(f"\nAccuracy on {data} ({len(recordings)} recordings, up to {frames} frames each):")
    print(
        f"{'recording':12s} {'split':6s} {'IoU mean':>8s} {'IoU min':>8s} {'absrel':>7s} "
        f"{'Z err':>6s} {'wide':>5s} {'X err':>6s} {'X-up':>6s}"
    )
    z_errors, all_ious, rels, wide_ok, x_errors = [], [], [], [], []
    for folder in recordings:
        rec = load_recording(folder, frames)
        cam, baseline = rec["calib"].left, rec["calib"].baseline_mm
        depth_est = make_depth_estimator("sgbm", **SIM_DEPTH_OPTIONS)
        segmenter = make_segmenter("colortrack")
        prompt = Prompt.from_box(rec["meta"]["prompt_box"])
        ious, rel = [], []
        first_depth = first_mask = None
        for i, (left, right) in enumerate(zip(rec["left"], rec["right"], strict=True)):
            depth = depth_est.depth_mm(left, right, cam, baseline)
            mask = segmenter.start(left, prompt, depth) if i == 0 else segmenter.track(left, depth)
            if i == 0:
                first_depth, first_mask = depth, mask
            truth_mask, truth_depth = rec["mask"][i], rec["depth"][i]
            ious.append(mask_iou(mask, truth_mask))
            inside = truth_mask & np.isfinite(truth_depth)
            rel.append(float(np.nanmean(np.abs(depth[inside] - truth_depth[inside]) / truth_depth[inside])))
        points = tissue_cloud(first_depth, first_mask, cam)
        frame = estimate_object_frame(points, up=rec["up"])
        truth = np.array(rec["truth"]["rotation"])
        z_err = angle_deg(frame.z_axis, truth[:, 2])
        wide = bool(frame.z_axis @ truth[:, 2] > 0)
        x_err = angle_deg(frame.x_axis, truth[:, 0]) if frame.x_axis @ truth[:, 0] > 0 else 180.0
        projected_up = rec["up"] - (rec["up"] @ frame.z_axis) * frame.z_axis
        x_up = angle_deg(frame.x_axis, projected_up)
        print(
            f"{folder.name:12s} {rec['meta'].get('split', ''):6s} {np.mean(ious):8.3f} {np.min(ious):8.3f} "
            f"{np.mean(rel) * 100:6.2f}% {z_err:6.2f} {'yes' if wide else 'NO':>5s} {x_err:6.2f} {x_up:6.2f}"
        )
        z_errors.append(z_err)
        all_ious += ious
        rels += rel
        wide_ok.append(wide)
        x_errors.append(x_err)
    print(
        f"{'all':12s} {'':6s} {np.mean(all_ious):8.3f} {np.min(all_ious):8.3f} {np.mean(rels) * 100:6.2f}% "
        f"{np.median(z_errors):6.2f} {sum(wide_ok)}/{len(wide_ok)} {np.median(x_errors):6.2f}"
    )
    print(
        "targets: IoU >= 0.9, depth abs-rel <= 3% inside the mask, Z error <= 3 deg median, wide end right "
        "in every recording, X within 3 deg of the projected up (X err: against the simulator's X)"
    )


def make_figures(data: Path, out_dir: Path) -> None:
    """The paper's Fig. 2 on a simulator recording (image, mask overlay, depth map, camera-frame
    cloud, object-frame cloud) and the SCARED depth comparison, as PNGs in out_dir."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    folder = sorted(p.parent for p in data.glob("*/meta.yaml"))[0]
    rec = load_recording(folder, 1)
    cam, baseline = rec["calib"].left, rec["calib"].baseline_mm
    left, right = rec["left"][0], rec["right"][0]
    depth = make_depth_estimator("sgbm", **SIM_DEPTH_OPTIONS).depth_mm(left, right, cam, baseline)
    mask = make_segmenter("colortrack").start(left, Prompt.from_box(rec["meta"]["prompt_box"]), depth)
    points = tissue_cloud(depth, mask, cam)
    frame = estimate_object_frame(points, up=rec["up"])
    local = frame.to_object(points)

    fig = plt.figure(figsize=(20, 4.2))
    rgb = cv2.cvtColor(left, cv2.COLOR_BGR2RGB)
    ax = fig.add_subplot(1, 5, 1)
    ax.imshow(rgb)
    x0, y0, x1, y1 = rec["meta"]["prompt_box"]
    ax.plot([x0, x1, x1, x0, x0], [y0, y0, y1, y1, y0], "y-", lw=1.5)
    ax.set_title("(a) left image + prompt box")
    ax = fig.add_subplot(1, 5, 2)
    overlay = rgb.copy()
    overlay[mask] = (0.5 * overlay[mask] + [0, 110, 0]).astype(np.uint8)
    ax.imshow(overlay)
    ax.contour(rec["mask"][0], levels=[0.5], colors="w", linewidths=0.8)
    ax.set_title(f"(b) mask (IoU {mask_iou(mask, rec['mask'][0]):.3f}; white: truth)")
    ax = fig.add_subplot(1, 5, 3)
    im = ax.imshow(depth, cmap="turbo", vmin=np.nanpercentile(depth, 1), vmax=np.nanpercentile(depth, 99))
    fig.colorbar(im, ax=ax, fraction=0.04, label="depth (mm)")
    ax.set_title("(c) depth (sgbm)")
    ax3 = fig.add_subplot(1, 5, 4, projection="3d")
    ax3.scatter(points[:, 0], points[:, 1], points[:, 2], s=1, c=points[:, 2], cmap="turbo")
    scale = 25.0
    for axis, colour in zip(frame.rotation.T, "rgb", strict=True):
        end = frame.origin + scale * axis
        ax3.plot(*zip(frame.origin, end, strict=True), color=colour, lw=2)
    ax3.set_title("(d) tissue cloud, camera frame (mm)")
    ax3.set_xlabel("x")
    ax3.set_ylabel("y")
    ax3.set_zlabel("z")
    ax3.invert_zaxis()
    ax3.view_init(elev=-60, azim=-90)
    ax4 = fig.add_subplot(1, 5, 5, projection="3d")
    ax4.scatter(local[:, 0], local[:, 1], local[:, 2], s=1, c=local[:, 2], cmap="viridis")
    for axis, colour in zip(np.eye(3), "rgb", strict=True):
        ax4.plot(*zip([0, 0, 0], scale * axis, strict=True), color=colour, lw=2)
    ax4.set_title("(e) object frame (X up, Z wide -> narrow)")
    ax4.set_xlabel("X")
    ax4.set_ylabel("Y")
    ax4.set_zlabel("Z")
    ax4.view_init(elev=15, azim=-60)
    for a in fig.axes[:3]:
        a.set_xticks([])
        a.set_yticks([])
    fig.tight_layout()
    fig.savefig(out_dir / "recon_fig2.png", dpi=90)
    plt.close(fig)

    if (SCARED / "left.png").is_file():
        left, right = cv2.imread(str(SCARED / "left.png")), cv2.imread(str(SCARED / "right.png"))
        gt = cv2.imread(str(SCARED / "disparity.tiff"), cv2.IMREAD_UNCHANGED)
        valid = (gt > 0) & (cv2.imread(str(SCARED / "occlusion.png"), cv2.IMREAD_UNCHANGED) != 128)
        raw = cv2.StereoSGBM_create(0, 96, 5, P1=600, P2=2400, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
        plain = raw.compute(left, right).astype(np.float32) / 16
        plain[plain <= 0] = np.nan
        ours = make_depth_estimator("sgbm").disparity(left, right)
        fig, axes = plt.subplots(1, 4, figsize=(20, 4.6))
        axes[0].imshow(cv2.cvtColor(left, cv2.COLOR_BGR2RGB))
        axes[0].set_title("SCARED left image")
        for ax, img, title in [
            (axes[1], np.where(valid, gt, np.nan), "ground truth (structured light)"),
            (axes[2], plain, "plain SGBM: 13% holes"),
            (axes[3], ours, "sgbm backend: every pixel"),
        ]:
            im = ax.imshow(img, cmap="turbo", vmin=15, vmax=90)
            ax.set_title(title)
        fig.colorbar(im, ax=list(axes), fraction=0.015, label="disparity (px)")
        for ax in axes:
            ax.set_xticks([])
            ax.set_yticks([])
        fig.savefig(out_dir / "recon_scared.png", dpi=80, bbox_inches="tight")
        plt.close(fig)
    print(f"figures written to {out_dir}")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, help="a synthesized preset folder (default: synthesize mini)")
    parser.add_argument("--frames", type=int, default=60, help="frames per recording for accuracy")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--speed-only", action="store_true")
    parser.add_argument("--figures", type=Path, metavar="DIR", help="only write the figures (docs/img)")
    args = parser.parse_args()
    cv2.setNumThreads(2)
    data = args.data or synthesize_data(args.frames)
    if args.figures:
        make_figures(data, args.figures)
        return
    first = sorted(p.parent for p in data.glob("*/meta.yaml"))[0]
    bench_speed(load_recording(first, min(args.frames, 30)), args.repeats)
    if not args.speed_only:
        bench_scared()
        bench_accuracy(data, args.frames)


if __name__ == "__main__":
    main()
