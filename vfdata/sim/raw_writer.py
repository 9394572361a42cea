"""Writing one simulated recording: render its frames as it is simulated, and write the raw recording
folder (the layout `vfdata convert` reads) with its ground truth. PNG, JPEG, NumPy and YAML writing is
deterministic: the same recording gives the same bytes.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import yaml

import vfdata
from vfdata.calibration import PinholeCamera, StereoCalibration
from vfdata.errors import InputError, VisionForceError
from vfdata.sim.png import encode_png16
from vfdata.sim.presets import FPS, RecordingPlan, counted_splits
from vfdata.sim.scene import SceneRenderer
from vfdata.sim.simulation import PHYSICS_HZ, Recording, sensor_samples, simulate

N_MATERIAL_POINTS = 2000
CAMERA_EPOCH_NS = 1_700_000_000_000_000_000

# Encoder settings, chosen for speed (CPU time per 640x512 frame on this project's machine): the
# stereo views as JPEG quality 95 (about 2.6 ms and 85 kB each; an endoscope recording is compressed
# video or JPEG too) or, on request, lossless PNG (about 20 ms each); the ground truth always lossless:
# the mask as run-length PNG (1 ms), the 16-bit depth with the SUB filter and zlib level 1 by our own
# writer (vfdata.sim.png: about 5 ms against 6-7 ms by OpenCV, the same 60-100 kB).
IMAGE_FORMATS = {
    "jpeg": (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 95]),
    "png": (".png", [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP,
                     cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]),
}
PNG_MASK = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE,
             cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]


def _encode(path: Path, image: np.ndarray, params: list[int] | None) -> None:
    """Encode and write one image: by OpenCV in the format the suffix names, or, with params None, as
    a 16-bit greyscale PNG by vfdata.sim.png (the ground-truth depth)."""
    if params is None:
        path.write_bytes(encode_png16(image))
        return
    ok, buf = cv2.imencode(path.suffix, image, params)
    if not ok:
        raise InputError(path, f"could not encode {path.suffix} image")
    path.write_bytes(buf)


def ground_truth_images(mask: np.ndarray, depth_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mask as uint8 0/255 and the depth (>= 0 mm) as uint16 in 0.1 mm, rounded half up."""
    depth = depth_mm * np.float32(10.0)
    depth += np.float32(0.5)
    np.minimum(depth, np.float32(65535.0), out=depth)
    return mask.view(np.uint8) * np.uint8(255), depth.astype(np.uint16)


def _quaternion(r: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion (x, y, z, w) with w >= 0."""
    w = np.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = np.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2
    y = np.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2
    z = np.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2
    x = np.copysign(x, r[2, 1] - r[1, 2])
    y = np.copysign(y, r[0, 2] - r[2, 0])
    z = np.copysign(z, r[1, 0] - r[0, 1])
    q = np.array([x, y, z, w])
    return q / np.linalg.norm(q)


def generator_key(preset: str, seed: int, plan: RecordingPlan, frames: int, image_format: str) -> dict:
    """What identifies a recording's output: a folder holding the same key is not made again. (The
    orientation was always in params.json, so folders made before it joined the key still match.)"""
    return {"generator": "vfdata synth", "version": vfdata.__version__, "preset": preset, "seed": int(seed),
            "recording": plan.id, "index": plan.index, "frames": int(frames), "image_format": image_format,
            "orientation_deg": number(plan.orientation_deg)}


def check_image_format(image_format: str) -> tuple[str, list[int]]:
    if image_format not in IMAGE_FORMATS:
        raise VisionForceError(f"unknown image format '{image_format}' (choose from {', '.join(IMAGE_FORMATS)})")
    return IMAGE_FORMATS[image_format]


def write_recording(rec: Recording, folder: Path, preset: str, seed: int, progress_counter=None,
                    image_format: str = "jpeg", test_orientations: Sequence[float] | None = None,
                    split_recordings: Mapping[str, int] | None = None) -> None:
    """Simulate and render `rec` into the (new, empty) raw recording folder `folder`, the stereo views
    as `image_format` ('jpeg' or 'png'); `test_orientations` and `split_recordings`, if the preset's were
    replaced, are named in the metadata's `source`."""
    suffix, image_params = check_image_format(image_format)
    spec = rec.spec
    cam = spec.cam.camera
    renderer = SceneRenderer(spec, rec.streams["render"])
    for sub in ("left", "right", "ground_truth/mask", "ground_truth/depth"):
        (folder / sub).mkdir(parents=True)
    tube = spec.tube
    s_pts, th_pts = tube.material_points(N_MATERIAL_POINTS)
    point_map = tube.surface_map(s_pts, th_pts)
    r_co, t_co = spec.object_to_camera()
    F = rec.frames
    points = np.zeros((F, N_MATERIAL_POINTS, 3), np.float32)
    normals = np.zeros((F, N_MATERIAL_POINTS, 3), np.float32)
    visible = np.zeros((F, N_MATERIAL_POINTS), bool)
    first_box: list[int] = []
    frame_times = np.zeros(F)

    def on_frame(i: int, t: float, grasp_o: np.ndarray, twist: float, jaw: float) -> None:
        nodes = rec.model.nodes
        frame = renderer.render(nodes, grasp_o, twist, jaw)
        name = f"{i:06d}"
        mask, depth = ground_truth_images(frame.mask, frame.depth_mm)
        writes = [(folder / "left" / (name + suffix), frame.left, image_params),
                  (folder / "right" / (name + suffix), frame.right, image_params),
                  (folder / "ground_truth/mask" / (name + ".png"), mask, PNG_MASK),
                  (folder / "ground_truth/depth" / (name + ".png"), depth, None)]
        # Encoding runs on a background thread (OpenCV releases the GIL), overlapping the next frame's
        # physics and rendering; at most a few frames wait, to bound memory.
        while len(pending) > 8:
            pending.pop(0).result()
        pending.extend(encoder.submit(_encode, *w) for w in writes)
        p, n = point_map.evaluate_scattered(nodes)
        p_c = p @ r_co.T + t_co
        n_c = n @ r_co.T
        points[i], normals[i] = p_c, n_c
        visible[i] = point_visibility(cam, p_c, n_c, frame.depth_mm, frame.mask)
        frame_times[i] = t
        if i == 0:
            ys, xs = np.nonzero(frame.mask)
            first_box.extend([int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1]
                             if len(xs) else [0, 0, cam.width, cam.height])
        if progress_counter is not None:
            with progress_counter.get_lock():
                progress_counter.value += 1

    pending: list = []
    with ThreadPoolExecutor(max_workers=1) as encoder:
        wrench = simulate(rec, on_frame)
        for job in pending:
            job.result()
    gt_force = np.stack([np.interp(frame_times, wrench[:, 0], wrench[:, c]) for c in range(1, 7)], axis=1)

    epoch = CAMERA_EPOCH_NS + rec.plan.index * 3_600_000_000_000
    frame_ns = epoch + np.round(np.arange(F) * 1e9 / FPS).astype(np.int64)
    with open(folder / "frames.csv", "w") as f:
        f.write("frame,timestamp_ns\n")
        f.writelines(f"{i},{t}\n" for i, t in enumerate(frame_ns))
    stamps, values = sensor_samples(rec, wrench)
    with open(folder / "force.csv", "w") as f:
        f.write("timestamp_ns,fx,fy,fz,tx,ty,tz\n")
        # One %-format per row (the same text as formatting each value): 27,000 rows per 815 frames.
        row_format = "%d," + ",".join(["%.6f"] * values.shape[1]) + "\n"
        f.writelines(row_format % (epoch + t, *row) for t, row in zip(stamps.tolist(), values.tolist(), strict=True))
    pos_m = spec.cam.position_w_mm * 1e-3
    q = _quaternion(spec.cam.rotation_wc)
    pose = ",".join(f"{v:.9f}" for v in (*pos_m, *q))
    with open(folder / "ecm_pose.csv", "w") as f:
        f.write("timestamp_ns,x,y,z,qx,qy,qz,qw\n")
        f.writelines(f"{t},{pose}\n" for t in frame_ns)
    k = cam.K
    StereoCalibration(cam.width, cam.height, k, np.zeros(5), k.copy(), np.zeros(5), np.eye(3),
                      np.array([-spec.cam.baseline_mm, 0.0, 0.0])).save(folder / "calibration.yaml")
    meta = {
        "study": rec.plan.tissue.study,
        "tissue": rec.plan.tissue.description,
        "orientation_deg": number(rec.plan.orientation_deg),
        "split": rec.plan.split,
        "prompt_box": first_box,
        "synthetic": True,
        "source": f"vfdata synth --preset {preset} --seed {seed}{_layout_options(test_orientations, split_recordings)} "
                  f"({rec.plan.id})",
    }
    (folder / "meta.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))

    gt = folder / "ground_truth"
    np.save(gt / "points.npy", points)
    np.save(gt / "normals.npy", normals)
    np.save(gt / "visible.npy", visible)
    np.save(gt / "force.npy", gt_force[:, :3].astype(np.float32))
    np.save(gt / "torque.npy", gt_force[:, 3:].astype(np.float32))
    sensor_origin = t_co + r_co @ np.array([0.0, 0.0, -spec.sensor_offset_mm])
    object_frame = {
        "frame": 0,
        "camera": "left rectified camera (x right, y down, z forward), mm",
        "rotation": r_co.round(9).tolist(),
        "origin_mm": t_co.round(6).tolist(),
        "axis": r_co[:, 2].round(9).tolist(),
        "wide_end_mm": t_co.round(6).tolist(),
        "free_end_mm": (t_co + r_co[:, 2] * tube.shape.length_mm).round(6).tolist(),
        "sensor": {"rotation": r_co.round(9).tolist(), "origin_mm": sensor_origin.round(6).tolist()},
    }
    (gt / "object_frame.json").write_text(json.dumps(object_frame, indent=2))
    params = {
        **generator_key(preset, seed, rec.plan, rec.frames, image_format),
        "tube": {"length_mm": tube.shape.length_mm, "base_radius_mm": tube.shape.base_radius_mm,
                 "tip_radius_mm": tube.shape.tip_radius_mm, "n_rings": tube.n_rings,
                 "n_around": tube.n_around, "mass_kg": rec.model.total_mass_kg},
        "material": rec.model.material.to_dict(),
        "sensor_offset_mm": spec.sensor_offset_mm,
        "sensor": rec.sensor,
        "grasp_fraction": rec.grasp_fraction,
        "physics_hz": PHYSICS_HZ,
        "camera": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width,
                   "height": cam.height, "baseline_mm": spec.cam.baseline_mm},
        "force_range_n": (gt_force[:, :3].max(0) - gt_force[:, :3].min(0)).round(3).tolist(),
        "trajectory": [{"t0": round(s.t0, 4), "t1": round(s.t1, 4), "kind": s.kind,
                        "to_mm": np.round(s.p1, 3).tolist(), "twist_deg": round(float(np.degrees(s.twist1)), 2)}
                       for s in rec.trajectory.segments if s.t0 < F / FPS],
    }
    (gt / "params.json").write_text(json.dumps(params, indent=2, default=float))


def point_visibility(camera: PinholeCamera, points_c: np.ndarray, normals_c: np.ndarray, depth_mm: np.ndarray,
                     mask: np.ndarray) -> np.ndarray:
    """Material points facing the camera, inside the tissue mask and not behind another surface."""
    facing = np.einsum("px,px->p", normals_c, -points_c) > 0
    uv = camera.project(points_c)
    ok = np.isfinite(uv).all(axis=1)
    u = np.full(len(uv), -1)
    v = np.full(len(uv), -1)
    u[ok] = np.floor(uv[ok, 0] + 0.5).astype(int)
    v[ok] = np.floor(uv[ok, 1] + 0.5).astype(int)
    ok &= (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    vis = np.zeros(len(uv), bool)
    idx = np.nonzero(ok & facing)[0]
    d = depth_mm[v[idx], u[idx]]
    z = points_c[idx, 2]
    vis[idx] = mask[v[idx], u[idx]] & (np.abs(d - z) < 0.3 + 0.01 * z)
    return vis


def number(x: float) -> int | float:
    """An integral value as an int: metadata and manifests say 90, not 90.0."""
    return int(x) if float(x).is_integer() else float(x)


def _layout_options(test_orientations: Sequence[float] | None, split_recordings: Mapping[str, int] | None) -> str:
    """The `vfdata synth` options that changed the preset's recordings, as typed."""
    orientations = "" if test_orientations is None else \
        " --test-orientations " + ",".join(str(number(a)) for a in test_orientations)
    counts = "".join(f" --{split}-recordings {n}" for split, n in counted_splits(split_recordings))
    return orientations + counts
