"""Which end is clamped: each cue of vfdata.recon.clamped_end on a scene built to answer one way, the vote, and
the look ahead of vfdata.tracking.motion_scan."""

import cv2
import numpy as np
import pytest

from vfdata.calibration import PinholeCamera
from vfdata.recon.clamped_end import STRONG, Cue, decide, fixture_cue, motion_cue, taper_cue
from vfdata.tracking.motion_scan import scan_motion, scan_stride

CAMERA = PinholeCamera(500.0, 500.0, 320.0, 256.0, 640, 512)


def test_the_taper_is_sure_of_a_clear_taper_and_not_of_noise():
    rng = np.random.default_rng(0)
    t = np.linspace(-50, 50, 24)
    tapered = taper_cue(t, 30 - 0.08 * t + rng.normal(0, 0.3, 24))  # wide at low t: clamped at the low end
    assert tapered.vote == 1 and tapered.strength > STRONG
    flat = taper_cue(t, 30 + rng.normal(0, 0.3, 24))
    assert flat.strength < STRONG
    assert taper_cue(t[:4], t[:4]).strength == 0  # too few slabs to say


def _scene(grey_beyond_low: bool, grey_beyond_high: bool = False):
    """A tube across the image at 100 mm (x from -40 to +40 mm), on a pink bed, with a grey block beyond an
    end (the clamp's fixture)."""
    image = np.full((512, 640, 3), (120, 110, 190), np.uint8)  # BGR: pink
    mask = np.zeros((512, 640), bool)
    x0, x1 = (int(CAMERA.cx + CAMERA.fx * v / 100) for v in (-40, 40))
    mask[236:276, x0:x1] = True
    image[mask] = (100, 100, 200)
    if grey_beyond_low:
        image[226:286, x0 - 30:x0 + 4] = (128, 128, 128)
    if grey_beyond_high:
        image[226:286, x1 - 4:x1 + 30] = (128, 128, 128)
    ends = np.array([[-40.0, 0.0, 100.0], [40.0, 0.0, 100.0]])
    return image, mask, ends


def test_the_fixture_is_seen_beyond_the_clamped_end():
    image, mask, ends = _scene(grey_beyond_low=True)
    cue = fixture_cue(image, mask, CAMERA, ends, np.array([1.0, 0.0, 0.0]), (8.0, 8.0))
    assert cue.vote == 1 and cue.strength > STRONG and cue.detail["metal_low"] > 0.8
    turned = fixture_cue(image, mask, CAMERA, ends[::-1], np.array([-1.0, 0.0, 0.0]), (8.0, 8.0))
    assert turned.vote == -1 and turned.strength > STRONG


def test_the_fixture_has_no_say_when_both_ends_or_neither_look_alike():
    for low, high in ((False, False), (True, True)):
        image, mask, ends = _scene(low, high)
        assert fixture_cue(image, mask, CAMERA, ends, np.array([1.0, 0.0, 0.0]), (8.0, 8.0)).strength < 1.0


def test_an_end_out_of_the_image_gives_the_fixture_no_say():
    image, mask, ends = _scene(grey_beyond_low=True)
    ends = ends.copy()
    ends[1, 0] = 500.0  # the free end far outside the view
    assert fixture_cue(image, mask, CAMERA, ends, np.array([1.0, 0.0, 0.0]), (8.0, 8.0)).strength == 0


def _pulled_tracks(moving_end: str, frames: int = 30, points: int = 200, reach_mm: float = 8.0):
    """Points along a tube on x (-50..50 mm): displacement grows from nothing at the clamped end."""
    rng = np.random.default_rng(1)
    x = rng.uniform(-50, 50, points)
    start = np.stack([x, rng.uniform(-5, 5, points), np.full(points, 100.0)], axis=1)
    share = (x + 50) / 100 if moving_end == "high" else (50 - x) / 100
    pull = np.linspace(0, reach_mm, frames)[:, None, None] * share[None, :, None] * np.array([0.0, 1.0, 0.3])
    return start[None] + pull + rng.normal(0, 0.1, (frames, points, 3)), np.ones((frames, points), bool)


@pytest.mark.parametrize("moving_end, vote", [("high", 1), ("low", -1)])
def test_the_motion_puts_the_clamp_at_the_end_that_stays(moving_end, vote):
    points, visible = _pulled_tracks(moving_end)
    cue = motion_cue(points, visible, np.array([1.0, 0.0, 0.0]), np.zeros(3))
    assert cue.vote == vote and cue.strength > STRONG


def test_no_motion_no_say():
    points, visible = _pulled_tracks("high", reach_mm=0.5)
    assert motion_cue(points, visible, np.array([1.0, 0.0, 0.0]), np.zeros(3)).strength == 0


def test_the_vote_follows_the_sure_cues_and_says_when_they_disagree():
    weak_taper, fixture = Cue("taper", -1, 1.5), Cue("fixture", 1, 12.0)
    verdict = decide([weak_taper, fixture])
    assert verdict.low_end_clamped and not verdict.doubtful
    torn = decide([Cue("taper", -1, 6.0), fixture])
    assert torn.low_end_clamped and torn.doubtful and not torn.agree
    unsure = decide([Cue("taper", 1, 2.0), Cue("fixture", 0, 0.0)])
    assert unsure.doubtful and unsure.agree
    assert (verdict.doubt, torn.doubt, unsure.doubt) == (None, "end", "end")


def test_a_taper_alone_against_two_sure_cues_is_its_own_doubt():
    """Glove 210's glove_006 (fresh sweep): taper 16.4 one way, fixture 12.3 and motion 9.6 the other; the
    end was the fixture's and the motion's, the frame 5.6 degrees off. Still doubtful, named for the taper."""
    outvoted = decide([Cue("taper", 1, 16.4), Cue("fixture", -1, 12.3), Cue("motion", -1, 9.6)])
    assert not outvoted.low_end_clamped and outvoted.doubtful and outvoted.doubt == "taper"
    # one sure cue for the verdict is not two: the end stays in doubt
    assert decide([Cue("taper", 1, 5.0), Cue("fixture", -1, 12.3), Cue("motion", -1, 2.0)]).doubt == "end"
    # a sure taper with a weak fixture and a sure motion against it: the taper is muted, the end theirs
    assert decide([Cue("taper", 1, 10.0), Cue("fixture", -1, 3.0), Cue("motion", -1, 9.0)]).doubt == "taper"
    # the fixture alone against the taper and the motion: not the taper's doubt
    assert decide([Cue("taper", 1, 5.0), Cue("fixture", -1, 12.3), Cue("motion", 1, 9.6)]).doubt == "end"


def test_a_sure_motion_outweighs_a_sure_taper_and_the_end_stays_in_doubt():
    """Colon 138's `colon_008` (fresh sweep, 201 degrees): the instrument's shaft along the tube made a taper of
    strength 10.4 one way, the grasper's motion 8.2 the other, the fixture unseen. The summed weights took the
    taper's end, and the frame came out 162 degrees off; the motion's end was the clamp's."""
    verdict = decide([Cue("taper", 1, 10.38), Cue("fixture", 0, 0.0), Cue("motion", -1, 8.23)])
    assert not verdict.low_end_clamped and verdict.doubtful and verdict.doubt == "end"
    # a taper that is not sure keeps its say (glove 218's glove_018: the motion 5.3 was wrong there; flagged)
    weak = decide([Cue("taper", -1, 2.68), Cue("fixture", 0, 0.0), Cue("motion", 1, 5.3)])
    assert weak.low_end_clamped and weak.doubtful and weak.margin == pytest.approx(2.62)


def test_the_scan_follows_the_moving_half_and_finds_the_end_that_stays():
    rng = np.random.default_rng(2)
    texture = cv2.GaussianBlur(rng.integers(0, 255, (512, 640), dtype=np.uint8), (0, 0), 2.0)
    frames = []
    for k in range(12):  # the right half slides down 2 px a frame; the left half stays
        image = texture.copy()
        image[:, 320:] = np.roll(texture[:, 320:], 2 * k, axis=0)
        frames.append(image)
    mask = np.zeros((512, 640), bool)
    mask[100:400, 40:600] = True
    depth = np.full((512, 640), 100.0, np.float32)
    points, visible = scan_motion(iter(frames), mask, depth, CAMERA)
    assert points.shape[0] == 12 and visible[-1].mean() > 0.5
    cue = motion_cue(points, visible, np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 100.0]))
    assert cue.vote == 1 and cue.strength > STRONG  # the clamp at low x, the left
    assert scan_stride(742) == 7 and scan_stride(50) == 1


def test_the_frame_carries_the_taper_doubt(monkeypatch):
    """`tissue_frame` writes the end decision's own reason into the frame's doubts (what `vfdata process`
    turns into the recording's verdict): `taper` for a taper outvoted by two sure cues."""
    from vfdata.calibration import PinholeCamera
    from vfdata.recon import tissue_frame as module
    from vfdata.recon.tube_axis import TubeAxis

    axis = TubeAxis(np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 120.0]), 0.0, 100)
    monkeypatch.setattr(module, "chosen_axis", lambda clouds: (axis, {"axis_doubtful": False}))
    outvoted = decide([Cue("taper", 1, 16.4), Cue("fixture", -1, 12.3), Cue("motion", -1, 9.6)])
    monkeypatch.setattr(module, "end_decision", lambda *args: outvoted)
    x = np.linspace(-40.0, 40.0, 50)
    cloud = np.stack([x, np.zeros_like(x), np.full_like(x, 120.0)], axis=1)
    depth = np.full((48, 64), 120.0, np.float32)
    frame = module.tissue_frame(np.zeros((48, 64, 3), np.uint8), np.ones((48, 64), bool), depth, cloud,
                                PinholeCamera(60.0, 60.0, 32.0, 24.0, 64, 48))
    assert frame.diagnostics["doubtful"] == ["taper"] and frame.z_axis @ axis.direction < 0
