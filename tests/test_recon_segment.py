"""Tissue segmentation: prompts, the colortrack default on synthetic and simulator videos, and the
model adapters' errors."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest
from recon_fixtures import load_sim_frames, make_sim_recording

from vfdata.errors import BackendError, InputError
from vfdata.recon import DetectorPrompt, Prompt, make_segmenter, mask_iou, segment_video

# ------------------------------------------------------------------------------------------ prompts


def test_prompt_parsing():
    p = Prompt.parse("box:100,80,400,300")
    assert p.box == (100, 80, 400, 300) and p.positive == ()
    p = Prompt.parse("points:320,240;300,200 neg:10,10")
    assert p.positive == ((320, 240), (300, 200)) and p.negative == ((10, 10),)
    p = Prompt.parse("box:1,2,30,40 points:5,6")
    assert p.box == (1, 2, 30, 40) and p.positive == ((5, 6),)


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty"),
        ("box:1,2,3", "cannot read"),
        ("box:10,10,5,5", "x1 > x0"),
        ("circle:1,2,3", "unknown part"),
        ("points:1;2", "cannot read"),
        ("neg:3,4", "positive point"),
    ],
)
def test_bad_prompts(text, message):
    with pytest.raises(InputError, match=message):
        Prompt.parse(text)


def test_prompt_outside_the_image_is_refused():
    frame = np.zeros((100, 120, 3), np.uint8)
    seg = make_segmenter("colortrack")
    with pytest.raises(InputError, match="outside the 120x100 image"):
        seg.start(frame, Prompt.parse("box:10,10,130,50"))
    with pytest.raises(InputError, match="outside"):
        seg.start(frame, Prompt.parse("points:-1,5"))


# ------------------------------------------------------------------------------ synthetic video


def _scene(t: int, instrument_x: float | None, h: int = 240, w: int = 320):
    """Pale pink textured tissue (an ellipse) on a dark red textured bed, with a grey instrument
    bar crossing it at column instrument_x; returns (BGR image, true visible-tissue mask)."""
    rng = np.random.default_rng(100 + t)
    yy, xx = np.mgrid[0:h, 0:w]
    cx = 160 + 2 * t  # the tissue slides to the right
    tissue = ((xx - cx) / 90.0) ** 2 + ((yy - 120) / 45.0) ** 2 <= 1
    image = np.empty((h, w, 3), np.float32)
    image[:] = (60, 60, 150)  # BGR dark red bed
    image[tissue] = (190, 195, 225)  # pale pink tissue
    image += rng.normal(0, 8, image.shape)
    visible = tissue.copy()
    if instrument_x is not None:
        bar = (np.abs(xx - instrument_x) < 12) & (yy < 150)
        image[bar] = (120, 120, 120)
        visible &= ~bar
    image = cv2.GaussianBlur(np.clip(image, 0, 255), (0, 0), 0.8).astype(np.uint8)
    return image, visible


def test_colortrack_follows_motion_and_cuts_out_the_instrument():
    instrument = [None] * 5 + [150.0, 165.0, 180.0, 195.0, 210.0] + [None] * 6
    frames, truth = zip(*[_scene(t, x) for t, x in enumerate(instrument)], strict=True)
    masks = segment_video(frames, "box:60,70,260,170")
    ious = [mask_iou(m, g) for m, g in zip(masks, truth, strict=True)]
    assert min(ious) > 0.9, [round(i, 3) for i in ious]
    # The instrument is out of the mask while it covers the tissue...
    covered = ~truth[7] & _scene(7, None)[1]
    assert masks[7][covered].mean() < 0.2
    # ... and the tissue it uncovered is back afterwards.
    assert mask_iou(masks[-1], truth[-1]) > 0.9


def test_track_before_start_and_size_change():
    seg = make_segmenter("colortrack")
    frame, _ = _scene(0, None)
    with pytest.raises(BackendError, match="before start"):
        seg.track(frame)
    seg.start(frame, Prompt.parse("box:60,70,260,170"))
    with pytest.raises(InputError, match="differs"):
        seg.track(cv2.resize(frame, (160, 120)))


def test_a_diagonal_tissue_takes_its_depth_from_the_middle_of_its_box():
    """A tissue band lying diagonally fills a quarter of its box; the rest is bed 45 mm behind it,
    partly as pale as the tissue. The first mask must be the band: the bed's depth is the box's median,
    which must not be taken for the tissue's (as it was: the mask then took in the pale bed)."""
    h, w = 240, 320
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:h, 0:w]
    band = np.abs((xx - 160) * 0.64 + (yy - 120) * 0.77) < 24  # through the centre, rising to the right
    pale_bed = ~band & (xx > 170) & (yy > 150) & (xx < 300) & (yy < 230)
    image = np.empty((h, w, 3), np.float32)
    image[:] = (60, 60, 150)
    image[band] = (190, 195, 225)
    image[pale_bed] = (180, 188, 222)
    image = cv2.GaussianBlur(np.clip(image + rng.normal(0, 8, image.shape), 0, 255), (0, 0), 0.8).astype(np.uint8)
    depth = np.where(band, 85.0, 130.0).astype(np.float32) + rng.normal(0, 0.5, (h, w)).astype(np.float32)
    ys, xs = np.nonzero(band & (xx > 20) & (xx < 300))
    box = f"box:{xs.min()},{ys.min()},{xs.max()},{ys.max()}"
    truth = band & (xx >= xs.min()) & (xx <= xs.max())
    mask = make_segmenter("colortrack").start(image, Prompt.parse(box), depth)
    assert mask_iou(mask, truth) > 0.85
    assert mask[pale_bed].mean() < 0.05


def test_a_highlight_is_metal_only_where_metal_surrounds_it():
    # a clamp's specular highlight is the clamp; a shine on wet tissue is the tissue
    from vfdata.recon.colortrack import metal_pixels

    image = np.zeros((60, 120, 3), np.uint8)
    image[:] = (120, 110, 200)  # pinkish tissue (BGR)
    image[:, 60:] = (128, 128, 128)  # grey metal on the right half
    image[20:30, 80:90] = 255  # a highlight on the metal
    image[20:30, 20:30] = 255  # a highlight on the tissue
    metal = metal_pixels(cv2.cvtColor(image, cv2.COLOR_BGR2Lab))
    assert metal[:, 60:].all()
    assert not metal[:, :60].any()


def test_a_prompt_off_the_tissue_is_a_clear_error():
    frame, _ = _scene(0, None)
    with pytest.raises(InputError, match="the first frame's mask is empty: the prompt does not cover the tissue"):
        make_segmenter("colortrack").start(frame, Prompt.parse("box:2,2,40,30"))


# ------------------------------------------------------------------------------- simulator video


@pytest.fixture(scope="module")
def sim_recording(tmp_path_factory):
    return make_sim_recording(tmp_path_factory.mktemp("sim"), index=0, frames=5)


def test_colortrack_on_the_simulator(sim_recording):
    data = load_sim_frames(sim_recording, 5)
    prompt = Prompt.from_box(data["prompt_box"])
    masks = make_segmenter("colortrack").segment_video(data["left"], prompt, depths=data["depth"])
    ious = [mask_iou(m, g) for m, g in zip(masks, data["mask"], strict=True)]
    assert np.mean(ious) >= 0.9, [round(i, 3) for i in ious]


# ---------------------------------------------------------------------------------- model adapters


def test_sam2_and_detector_fail_clearly_without_weights(tmp_path):
    with pytest.raises(BackendError, match="checkpoint"):
        make_segmenter("sam2")
    with pytest.raises(BackendError, match="not found"):
        make_segmenter("sam2", config="configs/sam2.1/sam2.1_hiera_l.yaml", checkpoint=tmp_path / "none.pt")
    with pytest.raises(BackendError, match="weights"):
        DetectorPrompt()
    with pytest.raises(BackendError, match="not found"):
        DetectorPrompt(weights=tmp_path / "none.pth")


def test_detector_without_torchvision_names_the_extra(tmp_path, monkeypatch):
    """torchvision is the optional extra `detector` (a CPU-only torch cannot have PyPI's torchvision):
    without it a detector with weights fails in one line that says what to install. A None in
    sys.modules makes the import fail as it does where the package is absent."""
    torch = pytest.importorskip("torch")
    torch.save({"x": torch.zeros(1)}, tmp_path / "det.pth")
    monkeypatch.setitem(sys.modules, "torchvision", None)
    monkeypatch.setitem(sys.modules, "torchvision.models.detection", None)
    with pytest.raises(BackendError, match=r"needs torchvision \(pip install 'visionforce\[detector\]'") as info:
        DetectorPrompt(weights=tmp_path / "det.pth")
    assert "\n" not in str(info.value)


@pytest.mark.slow
def test_detector_loads_a_state_dict_and_returns_a_box(tmp_path):
    torch = pytest.importorskip("torch")
    pytest.importorskip("torchvision")  # the optional extra `detector`
    from torchvision.models.detection import fasterrcnn_resnet50_fpn

    # An untrained detector saved as the user would save a fine-tuned one: loading must work,
    # and with random weights either a box inside the image or the clear "no box" error comes back.
    torch.manual_seed(0)
    model = fasterrcnn_resnet50_fpn(weights=None, weights_backbone=None, num_classes=2)
    torch.save({"model": model.state_dict()}, tmp_path / "det.pth")
    detector = DetectorPrompt(weights=tmp_path / "det.pth", min_score=0.0, min_size=160)
    frame, _ = _scene(0, None)
    try:
        prompt = detector(frame)
    except InputError as exc:
        assert "no tissue box" in str(exc)
    else:
        prompt.check_inside(frame.shape[1], frame.shape[0])
    with pytest.raises(BackendError, match="does not fit"):
        torch.save({"x": torch.zeros(1)}, tmp_path / "bad.pth")
        DetectorPrompt(weights=tmp_path / "bad.pth")


def test_unknown_segmenter():
    with pytest.raises(BackendError, match="colortrack, sam2"):
        make_segmenter("unet")

