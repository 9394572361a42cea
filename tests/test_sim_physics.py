"""Physics of the simulated tube: rest, stretch, viscosity, static balance, sensor read-out."""

from __future__ import annotations

import numpy as np
import pytest

from vfdata.sim.physics import GRAVITY_M_S2, UP, Material, TubeModel
from vfdata.sim.tissue import Tube, TubeShape


def make_model(**material) -> TubeModel:
    tube = Tube(TubeShape(60.0, 9.0, 7.5, n_rings=12, n_around=10), 1050.0, 1.5)
    return TubeModel(tube, Material(modulus_mpa=0.2, kind_factors=(1.0, 1.0, 0.5, 3.0, 0.5, 2.0), **material))


def grasp_nodes(model: TubeModel) -> np.ndarray:
    tube = model.tube
    rings = np.nonzero(np.abs(tube.ring_z - 45.0) <= 5.0)[0]
    return np.array([tube.node_index(r, c) for r in rings for c in (-1, 0, 1)])


def test_no_displacement_gives_only_the_offset():
    model = make_model()
    model.relax(tol_n=1e-10)
    tare = model.sensor_wrench()
    nodes = grasp_nodes(model)
    rest = model.x[nodes].copy()
    for _ in range(60):
        model.grasp(nodes, rest)
        model.step(1 / 60)
    w = model.sensor_wrench()
    assert np.abs(w.force_n - tare.force_n).max() < 1e-6
    assert np.abs(w.torque_nm - tare.torque_nm).max() < 1e-8
    # Untared, the sensor carries exactly the tissue's weight.
    np.testing.assert_allclose(tare.force_n, -model.total_mass_kg * GRAVITY_M_S2 * UP, atol=1e-8)


def test_force_grows_with_stretch_and_stiffens():
    model = make_model()
    model.relax(tol_n=1e-10)
    tare = model.sensor_wrench().force_n
    nodes = grasp_nodes(model)
    rest = model.x[nodes].copy()
    fz = []
    for d in (2.0, 4.0, 6.0, 8.0, 10.0):
        model.grasp(nodes, rest + [0.0, 0.0, d])
        model.relax(tol_n=1e-8)
        fz.append((model.sensor_wrench().force_n - tare)[2])
    fz = np.array(fz)
    assert (np.diff(fz) > 0).all(), fz  # pulling the free end away pulls the sensor along +Z
    assert (np.diff(fz, 2) > 0).all(), fz  # strain stiffening: each mm costs more than the last


def _ramp(model: TubeModel, speed_mm_s: float, distance_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Pull the grasped nodes along +Z at constant speed; return displacements and the force the
    tissue exerts on the grasper at each step."""
    model.relax(tol_n=1e-10)
    nodes = grasp_nodes(model)
    rest = model.x[nodes].copy()
    h = 1 / 120
    disp, force = [], []
    d = 0.0
    while d < distance_mm:
        d += speed_mm_s * h
        model.grasp(nodes, rest + [0.0, 0.0, d])
        model.step(h)
        disp.append(d)
        force.append(-model.grasp_force())
    return np.array(disp), np.array(force)


def test_viscous_part_opposes_the_velocity():
    elastic = make_model(kelvin_voigt_s=0.0, maxwell_ratio=0.0)
    viscous = make_model(kelvin_voigt_s=0.05, maxwell_ratio=0.0)
    d_e, f_e = _ramp(elastic, 20.0, 6.0)
    d_v, f_v = _ramp(viscous, 20.0, 6.0)
    np.testing.assert_allclose(d_e, d_v)
    extra = (f_v - f_e)[len(d_e) // 3:]  # after the start-up transient
    velocity = np.array([0.0, 0.0, 1.0])
    assert (extra @ velocity < -1e-3).all()  # the tissue resists the motion more when it is viscous
    # ... and more so when pulled faster.
    fast = make_model(kelvin_voigt_s=0.05, maxwell_ratio=0.0)
    d_f, f_f = _ramp(fast, 40.0, 6.0)
    at = 4.0
    extra_slow = np.interp(at, d_v, f_v[:, 2]) - np.interp(at, d_e, f_e[:, 2])
    el_fast = make_model(kelvin_voigt_s=0.0, maxwell_ratio=0.0)
    d_ef, f_ef = _ramp(el_fast, 40.0, 6.0)
    extra_fast = np.interp(at, d_f, f_f[:, 2]) - np.interp(at, d_ef, f_ef[:, 2])
    assert extra_fast < extra_slow < 0


def test_at_rest_the_clamp_balances_grasp_force_and_gravity():
    model = make_model()
    model.relax(tol_n=1e-10)
    nodes = grasp_nodes(model)
    model.grasp(nodes, model.x[nodes] + [4.0, -3.0, 5.0])
    model.relax(tol_n=1e-10)
    w = model.sensor_wrench()
    weight = -model.total_mass_kg * GRAVITY_M_S2 * UP
    np.testing.assert_allclose(w.force_n, model.grasp_force() + weight, atol=1e-6)
    assert np.linalg.norm(model.grasp_force()) > 1.0


def test_maxwell_branch_relaxes_while_holding():
    model = make_model(kelvin_voigt_s=0.0, maxwell_ratio=0.5, maxwell_tau_s=0.5)
    model.relax(tol_n=1e-10)
    tare = model.sensor_wrench().force_n[2]
    nodes = grasp_nodes(model)
    rest = model.x[nodes].copy()
    for k in range(1, 31):
        model.grasp(nodes, rest + [0.0, 0.0, 8.0 * k / 30])
        model.step(1 / 60)
    peak = model.sensor_wrench().force_n[2] - tare
    for _ in range(180):
        model.step(1 / 60)
    held = model.sensor_wrench().force_n[2] - tare
    assert 0 < held < 0.9 * peak


@pytest.mark.parametrize("twist", [0.3, -0.3])
def test_twist_gives_axial_torque_of_matching_sign(twist):
    model = make_model()
    model.relax(tol_n=1e-10)
    tare = model.sensor_wrench().torque_nm
    nodes = grasp_nodes(model)
    centre = model.x[nodes].mean(0) - [model.tube.ring_r.mean(), 0, 0]
    c, s = np.cos(twist), np.sin(twist)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    model.grasp(nodes, (model.x[nodes] - centre) @ rot.T + centre)
    model.relax(tol_n=1e-9)
    tz = (model.sensor_wrench().torque_nm - tare)[2]
    assert np.sign(tz) == np.sign(twist) and abs(tz) > 1e-4


def test_sensor_stream_with_no_load_reads_bias_and_noise_at_1khz():
    from vfdata.sim.presets import get_preset
    from vfdata.sim.synthesize import build_recording, sensor_samples

    rec = build_recording(get_preset("mini").recordings[0], seed=0, frames=60)
    t = np.arange(0, 2.1, 1 / 60)
    stamps, values = sensor_samples(rec, np.column_stack([t, np.zeros((len(t), 6))]))
    s = rec.sensor
    assert abs(np.median(np.diff(stamps)) - 1e6) < 1e4 and (np.diff(stamps) > 0).all()
    # The first sample is 0.1 s before the first frame, on a clock running ahead by the offset.
    assert abs(stamps[0] - (s["clock_offset_ns"] - 100_000_000)) < 1e6
    n = len(values)
    drift = np.asarray(s["force_drift_n_per_min"]) * (1.0 / 60)  # mean time about 1 s
    np.testing.assert_allclose(values[:, :3].mean(0), np.asarray(s["force_bias_n"]) + drift,
                               atol=4 * s["force_noise_n"] / np.sqrt(n) + 1e-3)
    np.testing.assert_allclose(values[:, 3:].mean(0), s["torque_bias_nm"], atol=4 * s["torque_noise_nm"] / np.sqrt(n))
    np.testing.assert_allclose(values[:, :3].std(0), s["force_noise_n"], rtol=0.15)
