"""The video-to-force clock offset (`vfdata sync`, vfdata.clock_offset) and `vfdata convert
--time-offset-ms`: found from synthetic signals with a known delay, from a simulated recording with a
planted one, and applied by the converter."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from vfdata.cli import main
from vfdata.clock_offset import GRID, estimate_offset, force_changes, pose_changes, recording_offsets
from vfdata.conversion.options import ConvertOptions
from vfdata.conversion.raw_folder import convert_raw_folder
from vfdata.errors import InputError
from vfdata.recording import Recording

FPS = 30.0


def _moves(seconds: float, seed: int, hz: float = 1000.0) -> tuple[np.ndarray, np.ndarray]:
    """(t (N,) s, x (N, 2) mm): minimum-jerk moves between random places with holds, sampled at `hz`."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / hz)
    x = np.zeros((len(t), 2))
    start, place = 0.0, np.zeros(2)
    while start < seconds:
        duration, hold = rng.uniform(0.3, 1.0), rng.uniform(0.0, 0.5)
        target = rng.uniform(-10, 10, 2)
        tau = np.clip((t - start) / duration, 0, 1)[:, None]
        moving = t >= start
        x[moving] = (place + (target - place) * (tau**3 * (10 - 15 * tau + 6 * tau**2)))[moving]
        start, place = start + duration + hold, target
    return t, x


def _motion_features(frame_s: np.ndarray, t: np.ndarray, x: np.ndarray, seed: int) -> np.ndarray:
    """Image motion features (F - 1, 2 * (GRID**2 + 1)) of a region moving with x: each cell sees the
    displacement through its own gain, plus flow noise (px per frame)."""
    rng = np.random.default_rng(seed)
    at = np.stack([np.interp(frame_s, t, x[:, c]) for c in range(2)], axis=1)
    velocity = np.diff(at, axis=0)
    gains = rng.uniform(0.5, 1.5, (GRID * GRID + 1, 2, 2))
    cells = np.einsum("kc,gdc->kgd", velocity, gains).reshape(len(velocity), -1)
    return cells + rng.normal(0, 0.02, cells.shape)


STIFFNESS = np.array([[0.08, 0.02, 0.01], [-0.03, 0.06, 0.02]])  # N per mm: two directions -> Fx Fy Fz
DAMPING = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0]]) * 1e-3  # N s per mm: the viscous force mostly along z


def _viscoelastic(delay_ms: float, damping: np.ndarray, seed: int = 1):
    """Force = K x + C dx/dt of a region moving by minimum-jerk moves, stamped `delay_ms` late:
    (motion features, frame_ns, force_ns, force)."""
    t, x = _moves(20.0, seed=seed)
    frame_s = np.arange(0.3, 19.7, 1 / FPS)
    force = x @ STIFFNESS + np.gradient(x, t, axis=0) @ damping
    force += np.random.default_rng(seed + 1).normal(0, 0.01, force.shape)
    frame_ns = np.round(frame_s * 1e9).astype(np.int64)
    force_ns = np.round(t * 1e9 + delay_ms * 1e6).astype(np.int64)
    return _motion_features(frame_s, t, x, seed=seed + 2), frame_ns, force_ns, force


@pytest.mark.parametrize("delay_ms", [-80.0, 0.0, 45.0])
def test_a_delay_planted_in_a_viscoelastic_force_is_found(delay_ms):
    """The offset is the delay; the viscous force's lead over the motion comes out apart from it."""
    motion, frame_ns, force_ns, force = _viscoelastic(delay_ms, DAMPING)
    estimate = estimate_offset("force", motion, frame_ns, force_ns, force_changes(frame_ns, force_ns, force),
                               max_offset_ns=200e6)
    assert estimate.offset_ns / 1e6 == pytest.approx(delay_ms, abs=4.0), estimate
    assert estimate.confident and estimate.fit_r2 > 0.8 and estimate.lead_ns > 5e6, estimate


def test_damping_in_proportion_to_stiffness_is_not_told_from_a_delay_and_says_so():
    """C = 20 ms x K: the force is K x(t + 20 ms) to first order, exactly what a clock 20 ms early
    gives: the data cannot tell them apart, and the estimate is not confident."""
    motion, frame_ns, force_ns, force = _viscoelastic(0.0, 0.020 * STIFFNESS)
    estimate = estimate_offset("force", motion, frame_ns, force_ns, force_changes(frame_ns, force_ns, force),
                               max_offset_ns=200e6)
    assert -25e6 < estimate.offset_ns < 1000 / FPS * 1e6 and not estimate.confident, estimate


def test_the_offset_of_a_moving_ecm_is_found():
    """The camera's motion moves the whole image without delay: the elastic fit alone."""
    t, x = _moves(20.0, seed=4, hz=100.0)
    frame_s = np.arange(0.3, 19.7, 1 / FPS)
    position_m = np.column_stack([x * 1e-3, np.zeros(len(t))])
    angle = np.radians(x[:, 0])  # it turns about z as it moves along x
    quaternion = np.column_stack([np.zeros((len(t), 2)), np.sin(angle / 2), np.cos(angle / 2)])
    frame_ns = np.round(frame_s * 1e9).astype(np.int64)
    pose_ns = np.round(t * 1e9 - 30e6).astype(np.int64)  # 30 ms early
    estimate = estimate_offset("ECM pose", _motion_features(frame_s, t, x, seed=5), frame_ns, pose_ns,
                               pose_changes(frame_ns, pose_ns, position_m, quaternion), max_offset_ns=200e6,
                               viscoelastic=False)
    assert estimate.offset_ns / 1e6 == pytest.approx(-30.0, abs=3.0) and estimate.confident, estimate


def test_too_little_overlap_is_no_estimate_with_the_reason():
    frame_ns = np.arange(50) * 33_333_333
    estimate = estimate_offset("force", np.zeros((49, 2 * (GRID * GRID + 1))), frame_ns, frame_ns,
                               lambda lag: np.zeros((49, 3)), max_offset_ns=500e6)
    assert estimate.offset_ns is None and "frame intervals" in estimate.reason and not estimate.confident


# ---- a simulated recording ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> Path:
    """The mini preset's validation recording alone (5 s), as `vfdata synth` writes it."""
    from vfdata.sim.presets import get_preset
    from vfdata.sim.raw_writer import write_recording
    from vfdata.sim.simulation import build_recording

    preset = get_preset("mini")
    plan = preset.recordings[1]
    folder = tmp_path_factory.mktemp("sync") / plan.id
    folder.mkdir()
    with threadpool_limits(1):  # the physics' small solves: 9x slower with OpenBLAS's threads on a busy machine
        write_recording(build_recording(plan, 0, None, preset.width, preset.height), folder, "mini", 0)
    return folder


def _plant(raw: Path, out: Path, planted_ms: float) -> Path:
    shutil.copytree(raw, out, ignore=shutil.ignore_patterns("ground_truth"))
    lines = (out / "force.csv").read_text().splitlines()
    shift = round(planted_ms * 1e6)
    (out / "force.csv").write_text("\n".join([lines[0]] + [f"{int(a) + shift},{b}" for a, b in
                                                            (line.split(",", 1) for line in lines[1:])]) + "\n")
    return out


def test_an_offset_planted_in_a_simulated_recording_is_found_and_convert_removes_it(simulated, tmp_path, capsys):
    sensor_ms = json.loads((simulated / "ground_truth" / "params.json").read_text())["sensor"]["clock_offset_ns"] / 1e6
    planted = _plant(simulated, tmp_path / "raw", 60.0)
    rec = convert_raw_folder(planted, tmp_path / "late.mcap", options=ConvertOptions(progress=False))
    found = recording_offsets(rec, max_offset_ms=200, progress=False)
    assert found.force.offset_ns / 1e6 == pytest.approx(60.0 + sensor_ms, abs=1000 / FPS), found.force
    assert found.force.confident and found.region is not None and found.pose.offset_ns is None  # a still ECM
    # the command says it, and the conversion it prints moves the force back onto the video's clock
    assert main(["sync", "--quiet", "--max-offset-ms", "200", str(rec)]) == 0
    out = capsys.readouterr().out
    line = next(line for line in out.splitlines() if "--time-offset-ms" in line)
    offset_ms = float(line.rsplit(" ", 1)[1])
    assert offset_ms == pytest.approx(found.force.offset_ns / 1e6, abs=0.05)
    aligned = tmp_path / "aligned.mcap"
    assert main(["convert", "--quiet", "--time-offset-ms", str(offset_ms), str(planted), str(aligned)]) == 0
    with Recording.open(rec) as late, Recording.open(aligned) as moved:
        assert np.array_equal(moved.force.times_ns, late.force.times_ns - round(offset_ms * 1e6))
        assert np.array_equal(moved.frame_times_ns, late.frame_times_ns)
        assert moved.metadata.extra["sensor_time_offset_ns"] == str(round(offset_ms * 1e6))
    again = recording_offsets(aligned, max_offset_ms=200, progress=False)
    assert abs(again.force.offset_ns / 1e6) < 1000 / FPS and again.applied_ns == round(offset_ms * 1e6)


def test_sync_json_and_its_errors(simulated, tmp_path, capsys):
    rec = convert_raw_folder(simulated, tmp_path / "rec.mcap", options=ConvertOptions(progress=False))
    assert main(["sync", "--quiet", "--json", "--max-frames", "100", "--max-offset-ms", "100", str(rec)]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["frames"] == 100 and set(result["force"]) >= {"offset_ms", "uncertainty_ms", "fit_r2", "confident"}
    assert main(["sync", "--max-offset-ms", "nan", str(rec)]) == 1
    assert main(["sync", str(tmp_path / "none.mcap")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert "--max-offset-ms: must be a positive number" in err[0] and "none.mcap" in err[1], err


def test_an_offset_that_moves_stamps_before_zero_is_refused(tmp_path, capsys):
    from rawfixtures import make_raw

    raw = make_raw(tmp_path / "raw", n=4)
    stamps = [line.split(",", 1) for line in (raw / "force.csv").read_text().splitlines()[1:]]
    first_ms = int(stamps[0][0]) / 1e6
    with pytest.raises(InputError, match=r"force\.csv: --time-offset-ms .* before 0"):
        convert_raw_folder(raw, tmp_path / "x.mcap", options=ConvertOptions(progress=False,
                                                                           time_offset_ns=round((first_ms + 1) * 1e6)))
    assert main(["convert", "--quiet", "--time-offset-ms", "inf", str(raw), str(tmp_path / "y.mcap")]) == 1
    assert "--time-offset-ms: must be a number" in capsys.readouterr().err
    assert not list(tmp_path.glob("*.mcap"))
