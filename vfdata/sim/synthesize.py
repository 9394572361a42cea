"""Orchestration: draw a recording's parameters, simulate the tissue and grasper, render the stereo
frames, and write the raw recording folder with its ground truth; then the dataset manifest.

Determinism: every recording draws from its own generators seeded by (seed, recording index, stream),
so the output does not depend on the number of workers or on the other recordings; PNG, NumPy and
YAML writers are deterministic, and BLAS runs single-threaded in the workers.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

import vfdata
from vfdata.atomic import atomic_output
from vfdata.calibration import PinholeCamera, StereoCalibration
from vfdata.errors import InputError, OutputExistsError, VisionForceError
from vfdata.sim.physics import Material, TubeModel
from vfdata.sim.png import encode_png16
from vfdata.sim.presets import BED_PALETTE, FPS, Preset, RecordingPlan, get_preset
from vfdata.sim.render import look_at, rotation_about, warm_up
from vfdata.sim.scene import CameraSetup, SceneRenderer, SceneSpec, object_rotation
from vfdata.sim.tissue import Tube, TubeShape
from vfdata.sim.trajectory import GraspTrajectory, MotionLimits, plan_trajectory

PHYSICS_HZ = 60.0
SENSOR_HZ = 1000.0
N_MATERIAL_POINTS = 2000
FOCAL_PX_AT_640 = 560.0
BASELINE_MM = 4.6
CLAMP_HEIGHT_MM = 40.0
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
_PNG_MASK = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE,
             cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]


# --- parameters ---------------------------------------------------------------------------------------


def _streams(seed: int, index: int) -> dict[str, np.random.Generator]:
    names = ("params", "texture", "motion", "sensor", "render")
    children = np.random.SeedSequence([seed, index]).spawn(len(names))
    return {n: np.random.default_rng(c) for n, c in zip(names, children, strict=True)}


@dataclass
class Recording:
    """A recording ready to simulate: tissue model, scene, grasper motion and sensor characteristics."""

    plan: RecordingPlan
    frames: int
    model: TubeModel
    spec: SceneSpec
    trajectory: GraspTrajectory
    grasp_fraction: float
    sensor: dict
    streams: dict[str, np.random.Generator]


def camera_model(width: int, height: int) -> PinholeCamera:
    f = FOCAL_PX_AT_640 * width / 640.0
    return PinholeCamera(f, f, (width - 1) / 2, (height - 1) / 2, width, height)


def build_recording(plan: RecordingPlan, seed: int, frames: int | None = None, width: int = 640,
                    height: int = 512) -> Recording:
    """Draw everything about one recording from (seed, plan.index)."""
    streams = _streams(seed, plan.index)
    rng = streams["params"]
    kind = plan.tissue

    def u(lo_hi: tuple[float, float]) -> float:
        return float(rng.uniform(*lo_hi))

    length = u(kind.length_mm)
    radius = u(kind.diameter_mm) / 2
    shape = TubeShape(length, radius, radius * u(kind.tip_ratio), kind.n_rings, kind.n_around)
    # The membrane modulus follows from the drawn pull stiffness of the tube (E * wall * 2 pi r / L),
    # so that tissue size and wall thickness do not scale the forces on their own.
    wall = u(kind.wall_mm)
    modulus = u(kind.axial_stiffness_n_mm) * length / (wall * 2 * np.pi * radius)
    material = Material(
        modulus_mpa=modulus, wall_mm=wall, density_kg_m3=kind.density_kg_m3,
        stiffening=u(kind.stiffening), compression_ratio=kind.compression_ratio,
        kelvin_voigt_s=u(kind.kelvin_voigt_s), maxwell_ratio=u(kind.maxwell_ratio),
        maxwell_tau_s=u(kind.maxwell_tau_s), kind_factors=kind.kind_factors,
    )
    tube = Tube(shape, material.density_kg_m3, material.wall_mm)
    sensor_offset = float(rng.uniform(18.0, 24.0))
    model = TubeModel(tube, material, sensor_offset_mm=sensor_offset)
    grasp_fraction = u(kind.grasp_fraction)

    # Camera: train/val look at the tube from its side; test recordings keep the tissue's new
    # orientation and get another viewpoint and another place in the image.
    test = plan.split == "test"
    rotation_wo = object_rotation(plan.orientation_deg)
    origin_w = np.array([0.0, 0.0, CLAMP_HEIGHT_MM])
    z_axis = rotation_wo[:, 2]
    # Aim at the middle of the grasper's working volume: along the tube and a little above it.
    reach_mid = 0.5 * (np.array(kind.reach_lo) + np.array(kind.reach_hi)) * length
    target = origin_w + z_axis * length * rng.uniform(0.5, 0.6) + np.array([0, 0, 0.8 * reach_mid[0]])
    target = target + rng.normal(0, 9.0 if test else 4.0, 3) * np.array([1, 1, 0.3])
    azimuth = np.radians(-90.0 + rng.uniform(-10, 10) + (rng.uniform(-35, 35) if test else 0.0))
    elevation = np.radians(rng.uniform(38, 62) if test else rng.uniform(45, 55))
    distance = min(150.0, u(kind.camera_distance_mm) * (rng.uniform(0.9, 1.1) if test else 1.0))
    eye = target + distance * np.array([np.cos(elevation) * np.cos(azimuth),
                                        np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    rotation_wc = look_at(eye, target, roll_rad=np.radians(rng.uniform(-8, 8)))
    cam = CameraSetup(camera_model(width, height), BASELINE_MM, rotation_wc, eye)

    # Instrument port: beside the endoscope port (to its right, a little above), so the shaft enters
    # from the side of the image.
    port_c = np.array([rng.uniform(55, 75) * rng.choice([-1.0, 1.0]), -rng.uniform(10, 25), rng.uniform(0, 15)])
    rcm_w = eye + rotation_wc @ port_c
    rcm_o = rotation_wo.T @ (rcm_w - origin_w)
    rest_top = np.array([np.interp(grasp_fraction * length, tube.ring_z, tube.ring_r), 0.0,
                         grasp_fraction * length])
    spec = SceneSpec(
        tube=tube, orientation_deg=plan.orientation_deg, rotation_wo=rotation_wo, origin_w_mm=origin_w,
        cam=cam, rcm_o_mm=rcm_o, grasp_point_o_mm=rest_top, tube_palette=kind.palette,
        bed_palette=BED_PALETTE, bed_depth_mm=CLAMP_HEIGHT_MM + rng.uniform(-5, 5),
        sensor_offset_mm=sensor_offset, exposure=float(rng.uniform(0.9, 1.2)),
        noise_sigma=float(rng.uniform(1.5, 3.0)), blur_sigma=float(rng.uniform(0.5, 0.8)),
        dense_s=kind.dense_s, dense_theta=kind.dense_theta,
    )
    n_frames = plan.frames if frames is None else int(frames)
    limits = MotionLimits(tuple(np.array(kind.reach_lo) * length), tuple(np.array(kind.reach_hi) * length))
    trajectory = plan_trajectory(streams["motion"], n_frames / FPS + 0.5, limits)
    srng = streams["sensor"]
    sensor = {
        "clock_offset_ns": int(srng.integers(2_000_000, 9_000_000)),
        "jitter_ns": 40_000.0,
        "force_bias_n": srng.normal(0, 0.15, 3).round(4).tolist(),
        "torque_bias_nm": srng.normal(0, 0.004, 3).round(6).tolist(),
        "force_noise_n": 0.03,
        "torque_noise_nm": 0.0006,
        "force_drift_n_per_min": srng.normal(0, 0.05, 3).round(4).tolist(),
    }
    return Recording(plan, n_frames, model, spec, trajectory, grasp_fraction, sensor, streams)


# --- simulation ------------------------------------------------------------------------------------


@dataclass
class _Grasp:
    nodes: np.ndarray
    offsets: np.ndarray  # node positions relative to the grasp point, un-twisted (object frame)


def grasped_nodes(model: TubeModel, z_mm: float, half_length_mm: float = 5.0) -> np.ndarray:
    """Nodes pinched by the jaws: the top three of each ring within the jaw length of z_mm."""
    tube = model.tube
    rings = np.nonzero(np.abs(tube.ring_z - z_mm) <= half_length_mm)[0]
    if len(rings) == 0:
        rings = np.array([int(np.argmin(np.abs(tube.ring_z - z_mm)))])
    around = np.array([-1, 0, 1])
    return np.array([tube.node_index(r, c) for r in rings for c in around])


def simulate(rec: Recording, on_frame) -> np.ndarray:
    """Run the physics at PHYSICS_HZ; call on_frame(frame_index, t_s, grasp_point, twist, jaw) at each
    camera frame. Returns (steps, 7): time (s) and the tared sensor wrench (N, N m) at every step."""
    model = rec.model
    model.release()
    model.relax(tol_n=1e-8)
    tare = model.sensor_wrench()
    # Rest grasp point: the top of the (sagged) tube at the grasp position.
    z_g = rec.grasp_fraction * model.tube.shape.length_mm
    nodes = grasped_nodes(model, z_g)
    g0 = model.x[nodes].mean(axis=0) + np.array([model.tube.ring_r.max() * 0.05, 0, 0])
    steps_per_frame = int(round(PHYSICS_HZ / FPS))
    h = 1.0 / PHYSICS_HZ
    n_steps = rec.frames * steps_per_frame
    times = np.arange(n_steps + 1) * h
    disp, twist, jaw, holding = rec.trajectory(times)
    grasp: _Grasp | None = None
    out = np.zeros((n_steps + 1, 7))
    out[:, 0] = times
    z = np.array([0.0, 0.0, 1.0])
    for k in range(n_steps + 1):
        g = g0 + disp[k]
        if k > 0:
            if holding[k]:
                if grasp is None:
                    rot_inv = rotation_about(z, -twist[k])
                    grasp = _Grasp(nodes, (model.x[nodes] - g) @ rot_inv.T)
                targets = g + grasp.offsets @ rotation_about(z, twist[k]).T
                model.grasp(grasp.nodes, targets)
            else:
                grasp = None
                model.release()
            model.step(h)
        w = model.sensor_wrench()
        out[k, 1:4] = w.force_n - tare.force_n
        out[k, 4:7] = w.torque_nm - tare.torque_nm
        if k % steps_per_frame == 0 and k // steps_per_frame < rec.frames:
            on_frame(k // steps_per_frame, times[k], g, float(twist[k]), float(jaw[k]))
    return out


def sensor_samples(rec: Recording, wrench: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """1 kHz sensor readings on the sensor clock: (timestamps_ns relative to the camera epoch, (N, 6)
    values) with bias, drift, noise and timing jitter. The sensor runs from 0.1 s before the first
    frame to 0.1 s after the last."""
    s = rec.sensor
    rng = rec.streams["sensor"]
    duration = (rec.frames - 1) / FPS
    k = np.arange(int(round((duration + 0.2) * SENSOR_HZ)) + 1)
    t_true = k / SENSOR_HZ - 0.1 + rng.normal(0, s["jitter_ns"] * 1e-9, len(k))
    t_true = np.maximum.accumulate(t_true)
    values = np.stack([np.interp(t_true, wrench[:, 0], wrench[:, c], left=0.0) for c in range(1, 7)], axis=1)
    values[:, :3] += np.asarray(s["force_bias_n"]) + np.outer(t_true / 60.0, s["force_drift_n_per_min"])
    values[:, 3:] += np.asarray(s["torque_bias_nm"])
    values[:, :3] += rng.normal(0, s["force_noise_n"], (len(k), 3))
    values[:, 3:] += rng.normal(0, s["torque_noise_nm"], (len(k), 3))
    stamps = np.round(t_true * 1e9).astype(np.int64) + s["clock_offset_ns"]
    return stamps, values


# --- writing -----------------------------------------------------------------------------------------


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
    """What identifies a recording's output: a folder holding the same key is not made again."""
    return {"generator": "vfdata synth", "version": vfdata.__version__, "preset": preset, "seed": int(seed),
            "recording": plan.id, "index": plan.index, "frames": int(frames), "image_format": image_format}


def _check_image_format(image_format: str) -> tuple[str, list[int]]:
    if image_format not in IMAGE_FORMATS:
        raise VisionForceError(f"unknown image format '{image_format}' (choose from {', '.join(IMAGE_FORMATS)})")
    return IMAGE_FORMATS[image_format]


def write_recording(rec: Recording, folder: Path, preset: str, seed: int, progress_counter=None,
                    image_format: str = "jpeg") -> None:
    """Simulate and render `rec` into the (new, empty) raw recording folder `folder`, the stereo views
    as `image_format` ('jpeg' or 'png')."""
    suffix, image_params = _check_image_format(image_format)
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
                  (folder / "ground_truth/mask" / (name + ".png"), mask, _PNG_MASK),
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
        "orientation_deg": _number(rec.plan.orientation_deg),
        "split": rec.plan.split,
        "prompt_box": first_box,
        "synthetic": True,
        "source": f"vfdata synth --preset {preset} --seed {seed} ({rec.plan.id})",
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
        "orientation_deg": rec.plan.orientation_deg,
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


# --- the dataset ------------------------------------------------------------------------------------------


def _number(x: float) -> int | float:
    return int(x) if float(x).is_integer() else float(x)


def manifest(preset: Preset, root: str) -> dict:
    """The dataset manifest (docs/architecture.md) of a preset, with recordings under `root`."""
    return {
        "name": preset.name,
        "root": root,
        "recordings": [{"id": r.id, "orientation_deg": _number(r.orientation_deg), "split": r.split}
                       for r in preset.recordings],
    }


def _is_complete(folder: Path, key: dict) -> bool:
    params = folder / "ground_truth" / "params.json"
    if not params.is_file():
        return False
    try:
        stored = json.loads(params.read_text())
    except (OSError, ValueError):
        return False
    return all(stored.get(k) == v for k, v in key.items())


_COUNTER = None


def _init_worker(counter) -> None:
    global _COUNTER
    _COUNTER = counter
    cv2.setNumThreads(1)


def _make_one(args: tuple[str, int, int, str, int | None, str]) -> str:
    """Worker: make one recording (the parent already checked what may be replaced)."""
    preset_name, seed, index, out_dir, frames, image_format = args
    preset = get_preset(preset_name)
    plan = preset.recordings[index]
    rec = build_recording(plan, seed, frames, preset.width, preset.height)
    target = Path(out_dir) / plan.id
    key = generator_key(preset_name, seed, plan, rec.frames, image_format)
    if _is_complete(target, key):
        if _COUNTER is not None:
            with _COUNTER.get_lock():
                _COUNTER.value += rec.frames
        return "kept"
    with atomic_output(target, overwrite=True) as tmp:
        tmp.mkdir()
        write_recording(rec, tmp, preset_name, seed, _COUNTER, image_format)
    return "made"


def synthesize(preset: str, out_dir: str | Path, seed: int = 0, workers: int = 1, progress: bool = True,
               frames: int | None = None, overwrite: bool = False, image_format: str = "jpeg") -> Path:
    """Write the preset's recordings under out_dir (one raw folder each, with ground_truth/) and
    `<preset>.manifest.yaml`; returns the manifest path. The stereo views are JPEG (quality 95) or,
    with image_format='png', lossless PNG. Recordings already made with the same generator settings
    are kept; other existing ones are refused unless `overwrite`."""
    p = get_preset(preset)
    _check_image_format(image_format)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(out, "output exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    if frames is not None and frames < 1:
        raise InputError(out, "--frames must be at least 1")
    if not overwrite:
        for plan in p.recordings:
            target = out / plan.id
            if target.exists():
                key = generator_key(preset, seed, plan, plan.frames if frames is None else frames, image_format)
                if not _is_complete(target, key):
                    raise OutputExistsError(target)
    total = sum(r.frames if frames is None else frames for r in p.recordings)
    jobs = [(preset, int(seed), r.index, str(out), frames, image_format) for r in p.recordings]
    # Workers are fresh processes with single-threaded BLAS: faster on few cores, and the same
    # floating-point results whatever the number of workers.
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    os.environ["OMP_NUM_THREADS"] = "1"
    os.environ["MKL_NUM_THREADS"] = "1"
    # Compile the renderer's kernels here, once (or load them from numba's cache), so that no worker
    # compiles them (each would, at the same time, on a first run).
    warm_up()
    ctx = mp.get_context("spawn")
    counter = ctx.Value("q", 0)
    from tqdm import tqdm

    with ProcessPoolExecutor(max_workers=max(1, int(workers)), mp_context=ctx, initializer=_init_worker,
                             initargs=(counter,)) as pool, \
            tqdm(total=total, unit="frame", desc=f"synth {preset}", disable=not progress) as bar:
        futures = [pool.submit(_make_one, job) for job in jobs]
        while not all(f.done() for f in futures):
            time.sleep(0.2)
            bar.update(counter.value - bar.n)
        for f in futures:
            f.result()
        bar.update(counter.value - bar.n)
    path = out / f"{preset}.manifest.yaml"
    with atomic_output(path, overwrite=True) as tmp:
        tmp.write_text(yaml.safe_dump(manifest(p, "."), sort_keys=False))
    return path
