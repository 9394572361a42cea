"""The frames where the tissue rests again, and the axis the fits there agree on (vfdata.recon.rest_frames)."""

import numpy as np
import pytest

from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder
from vfdata.engine import EngineOptions
from vfdata.recon.rest_frames import (
    MAX_REST_FRAMES,
    REST_AFTER_FRAMES,
    REST_MM,
    TRIM_DEG,
    confirming_fits,
    mean_direction,
    rest_frames,
    trimmed_direction,
)
from vfdata.recording import Recording
from vfdata.rig import rig_for
from vfdata.sim import synthesize
from vfdata.tracking.motion_scan import LookAhead


def turned(deg: float, about: str = "y") -> np.ndarray:
    """The unit Z axis turned by `deg` degrees about x or y."""
    a = np.radians(deg)
    return np.array([np.sin(a), 0.0, np.cos(a)]) if about == "y" else np.array([0.0, np.sin(a), np.cos(a)])


def angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(a @ b) / np.linalg.norm(a) / np.linalg.norm(b)))))


def test_rest_frames_are_those_back_where_they_were_after_the_first_second():
    rng = np.random.default_rng(0)
    first = rng.uniform(-30, 30, (50, 3))
    indices = list(range(0, 300, 10))
    # pulled 6 mm at frames 40-150, back within 0.5 mm elsewhere
    shift = np.array([6.0 if 40 <= i <= 150 else 0.5 for i in indices])
    points = first[None] + shift[:, None, None] * np.array([1.0, 0.0, 0.0])
    visible = np.ones(points.shape[:2], bool)
    frames = rest_frames(points, visible, indices)
    assert len(frames) == MAX_REST_FRAMES
    assert all(i >= REST_AFTER_FRAMES and not 40 <= i <= 150 for i in frames)
    assert frames == sorted(frames) and frames[0] == REST_AFTER_FRAMES and frames[-1] == indices[-1]
    # a pull just over the rest threshold everywhere: no frame rests
    pulled = np.repeat(first[None], len(indices), axis=0)
    pulled[1:, :, 0] += REST_MM
    assert rest_frames(pulled, visible, indices) == []
    # points lost: a frame whose rest cannot be told is passed over
    lost = visible.copy()
    lost[-1, :45] = False
    assert indices[-1] not in rest_frames(points, lost, indices)


def test_mean_direction_takes_every_line_to_the_first_ones_side():
    mean = mean_direction(turned(0), [-turned(4), turned(-4)])
    assert angle(mean, turned(0)) < 1e-9 and mean[2] > 0


def test_the_axis_of_the_first_and_resting_frames_leaves_a_stray_fit_out():
    # the first frame agrees with the resting ones: their mean, near the first
    assert angle(trimmed_direction(turned(0), [turned(2), turned(-2), turned(1)]), turned(0.25)) < 1e-3
    # one resting frame seen badly (a pull along the line of sight) is left out: the others' mean
    assert angle(trimmed_direction(turned(0), [turned(30), turned(1), turned(-1)]), turned(0)) < 1e-3
    # an occluded first frame, 12 degrees off, is left out of three resting frames that agree (one reversed)
    axis = trimmed_direction(turned(12, "x"), [turned(1), -turned(-1), turned(0)])
    assert angle(axis, turned(0)) < 1e-3 and axis @ turned(12, "x") > 0
    # one far stray among three fits, which drags the mean of all beyond TRIM_DEG of every fit: left out
    assert angle(trimmed_direction(turned(0), [turned(1), turned(25)]), turned(0.5)) < 1e-3
    # two fits TRIM_DEG and more apart: their mean
    assert angle(trimmed_direction(turned(0), [turned(2 * TRIM_DEG)]), turned(TRIM_DEG)) < 1e-3
    assert angle(trimmed_direction(turned(0), [turned(30)]), turned(15)) < 1e-3
    assert angle(trimmed_direction(turned(7), []), turned(7)) < 1e-9


def test_resting_fits_confirm_the_axis_within_the_trim_either_sign():
    assert confirming_fits(turned(0), [turned(TRIM_DEG - 0.5), -turned(-2), turned(TRIM_DEG + 0.5)]) == 2
    assert confirming_fits(turned(0), []) == 0
    assert type(confirming_fits(turned(0), [turned(1)])) is int  # written into the derived metadata as JSON


@pytest.mark.parametrize("rest_deg, doubted", [((1.0, -1.0), False), ((1.0,), True), ((1.0, 15.0), True), ((), True)])
def test_resting_frames_that_agree_lift_the_first_frames_axis_doubt(monkeypatch, rest_deg, doubted):
    """The first frame doubts its own fit; two resting frames whose fits agree on the axis taken lift that
    doubt, one alone or one stray does not (a stray is left out of the mean, so it confirms nothing)."""
    from vfdata.calibration import PinholeCamera
    from vfdata.recon import tissue_frame as module
    from vfdata.recon.clamped_end import Cue, decide
    from vfdata.recon.tube_axis import TubeAxis

    def tube(deg: float) -> TubeAxis:
        return TubeAxis(turned(deg), np.array([0.0, 0.0, 120.0]), 0.0, 100)

    monkeypatch.setattr(module, "chosen_axis", lambda clouds: (tube(0), {"axis_doubtful": True}))
    monkeypatch.setattr(module, "end_decision", lambda *args: decide([Cue("fixture", 1, 12.0)]))
    x = np.linspace(-40.0, 40.0, 50)
    cloud = np.stack([np.zeros_like(x), np.zeros_like(x), 120.0 + x], axis=1)
    camera = PinholeCamera(60.0, 60.0, 32.0, 24.0, 64, 48)
    frame = module.tissue_frame(np.zeros((48, 64, 3), np.uint8), np.ones((48, 64), bool),
                                np.full((48, 64), 120.0, np.float32), cloud, camera,
                                rest_axes={40 + k: tube(d) for k, d in enumerate(rest_deg)} or None)
    assert ("axis" in frame.diagnostics["doubtful"]) == doubted
    assert frame.diagnostics["axis_doubtful"]  # the first frame's own judgement is kept beside
    if rest_deg:  # the stray of 15 degrees is left out of the mean, and confirms nothing
        assert frame.diagnostics["rest"]["confirming"] == sum(abs(d) <= TRIM_DEG for d in rest_deg)


def test_processing_fits_the_axis_again_at_the_frames_where_the_tissue_rests(tmp_path):
    """The engine's look ahead, wired through: a recording whose tissue stays where it was (every frame the
    first one's pair) rests at frames 30 and on; the axis is fitted there too, and since each sees the
    same tissue, it stays where the first frame put it."""
    synthesize("mini", tmp_path, seed=1, frames=2, workers=1, progress=False)
    path = convert_raw_folder(tmp_path / "mini_002", tmp_path / "mini_002.mcap", options=ConvertOptions(progress=False))
    with Recording.open(path) as rec:
        rig = rig_for(rec, path)
        engine = rig.engine(rig.stage_options(EngineOptions(tracker="none")), rig.prompt(None))
        first = rec.rectified_frame(0)
        engine.look_ahead = LookAhead(90, lambda i: first.left, lambda i: (first.left, first.right))
        engine.step(0, first.stamp_ns, first.left, first.right)
    rest = engine.frame.diagnostics["rest"]
    assert len(rest["frames"]) == MAX_REST_FRAMES and min(rest["frames"]) >= REST_AFTER_FRAMES
    assert max(rest["deg"]) < 2.0 and rest["moved_deg"] < 2.0
    assert angle(np.asarray(rest["first"]), engine.frame.z_axis) == pytest.approx(rest["moved_deg"], abs=0.01)
