"""One simulated recording before it is written: its parameters drawn from the preset's ranges, the
physics of the tissue under the grasper, and the force sensor's readings.

Every recording draws from its own generators seeded by (seed, recording index, stream), so it does
not depend on the other recordings nor on the number of worker processes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.sim.physics import Material, TubeModel
from vfdata.sim.presets import BED_PALETTE, FPS, RecordingPlan
from vfdata.sim.render import look_at, rotation_about
from vfdata.sim.scene import CameraSetup, SceneSpec, object_rotation
from vfdata.sim.tissue import Tube, TubeShape
from vfdata.sim.trajectory import GraspTrajectory, MotionLimits, plan_trajectory

PHYSICS_HZ = 60.0
SENSOR_HZ = 1000.0
FOCAL_PX_AT_640 = 560.0
BASELINE_MM = 4.6
CLAMP_HEIGHT_MM = 40.0


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
