"""The tracker registry: every tracker built by name and fed FrameInputs gives the points its own class
gives when called directly, and wrong use is refused by name."""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest
import torch

from vfdata.errors import BackendError, InputError
from vfdata.tracking import (
    TRACKERS,
    FrameInputs,
    GeometryTracker,
    GroundTruthTracker,
    KLTTracker,
    make_tracker,
    select_reference_points,
)
from vfdata.tracking.synthetic import CAMERA, DeformingSheet, press_and_stretch

FRAMES = 4
POINTS = 48


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def scene():
    """A pressed and stretched sheet: per frame the BGR image, mask, depth (mm) and cloud, and the
    material points and normals of its ground truth."""
    sheet = DeformingSheet(press_and_stretch(FRAMES))
    frames = []
    for f in range(FRAMES):
        grey, mask, depth = sheet.image(f)
        frames.append({"image": cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR), "mask": mask,
                       "depth": depth.astype(np.float32), "cloud": sheet.cloud(f, 4000)})
    uv = sheet.material_grid(60)
    material = np.stack([sheet.surface(uv, f) for f in range(FRAMES)])
    normals = np.stack([sheet.normals(uv, f) for f in range(FRAMES)])
    return frames, (material, normals)


def inputs(frame: dict, index: int) -> FrameInputs:
    return FrameInputs(index=index, camera=CAMERA, image_bgr=frame["image"], depth_mm=frame["depth"],
                       mask=frame["mask"], cloud_mm=frame["cloud"])


def direct(name: str, frames: list[dict], ground_truth) -> list[tuple[np.ndarray, np.ndarray]]:
    """(points, visible) per frame from the tracker's own class, called as its docstring says."""
    first = frames[0]
    if name in ("geometry", "geometry+"):
        extra = {"reference_image": first["image"]} if name == "geometry+" else {}
        tracker = GeometryTracker(first["cloud"], camera=CAMERA, num_points=POINTS, seed=3, mode=name, **extra)
        step = lambda f, fr: tracker.update(fr["cloud"], fr["mask"], fr["image"] if name == "geometry+" else None)  # noqa: E731
    elif name == "klt":
        tracker = KLTTracker(first["cloud"], CAMERA, first["image"], num_points=POINTS, seed=3)
        step = lambda f, fr: tracker.update(fr["image"], fr["depth"], fr["mask"])  # noqa: E731
    elif name == "groundtruth":
        tracker = GroundTruthTracker(first["cloud"], *ground_truth, camera=CAMERA, num_points=POINTS, seed=3)
        step = lambda f, fr: tracker.update(f, fr["mask"])  # noqa: E731
    else:  # static: the reference selection, standing still
        reference = first["cloud"][select_reference_points(first["cloud"], POINTS, 3)]
        return [(reference, CAMERA.in_mask(reference, fr["mask"])) for fr in frames]
    out = [(tracker.reference, CAMERA.in_mask(tracker.reference, first["mask"]))]
    out += [step(f, frames[f]) for f in range(1, len(frames))]
    return out


@pytest.mark.parametrize("name", [n for n in TRACKERS if n != "cotracker"])
def test_each_tracker_gives_the_points_of_its_own_class(scene, name):
    frames, ground_truth = scene
    tracker = make_tracker(name, inputs(frames[0], 0), num_points=POINTS, seed=3, ground_truth=ground_truth)
    assert tracker.name == name and not tracker.offline
    got = [(tracker.points, tracker.visible)]
    got += [tracker.update(inputs(frames[f], f)) for f in range(1, FRAMES)]
    expected = direct(name, frames, ground_truth)
    for (points, visible), (want_points, want_visible) in zip(got, expected, strict=True):
        assert points.shape == (POINTS, 3) and visible.shape == (POINTS,) and visible.dtype == bool
        np.testing.assert_array_equal(points, want_points)
        np.testing.assert_array_equal(visible, want_visible)
    np.testing.assert_array_equal(tracker.points, got[-1][0])
    # The tracker moved (all but the static one), and every tracker started from the same points.
    assert name == "static" or not np.array_equal(got[-1][0], got[0][0])
    np.testing.assert_array_equal(got[0][0], direct("static", frames[:1], None)[0][0])


def test_a_tracker_reads_only_the_inputs_it_names(scene):
    frames, ground_truth = scene
    for name in ("geometry", "groundtruth", "static"):
        tracker = make_tracker(name, inputs(frames[0], 0), num_points=POINTS, seed=3, ground_truth=ground_truth)
        assert "image_bgr" not in tracker.inputs
        given = {field: getattr(inputs(frames[1], 1), field) for field in tracker.inputs}
        tracker.update(FrameInputs(index=1, camera=CAMERA, **given))
    klt = make_tracker("klt", inputs(frames[0], 0), num_points=POINTS, seed=3)
    with pytest.raises(BackendError, match="needs depth_mm, image_bgr of frame 1"):
        klt.update(FrameInputs(index=1, camera=CAMERA, mask=frames[1]["mask"]))


def test_ground_truth_from_its_folder_equals_the_arrays(scene, tmp_path):
    frames, (material, normals) = scene
    np.save(tmp_path / "points.npy", material.astype(np.float32))
    np.save(tmp_path / "normals.npy", normals.astype(np.float32))
    from_folder = make_tracker("groundtruth", inputs(frames[0], 0), POINTS, 3, ground_truth=tmp_path)
    from_arrays = make_tracker("groundtruth", inputs(frames[0], 0), POINTS, 3,
                               ground_truth=(material.astype(np.float32), normals.astype(np.float32)))
    third = inputs(frames[2], 2)
    np.testing.assert_array_equal(from_folder.update(third)[0], from_arrays.update(third)[0])
    with pytest.raises(InputError, match="no frame 9"):
        from_folder.update(inputs(frames[2], 9))


def test_wrong_names_options_and_calls_are_refused(scene, tmp_path):
    frames, _ = scene
    first = inputs(frames[0], 0)
    with pytest.raises(BackendError, match="unknown tracker 'sift'.*geometry, geometry\\+, klt"):
        make_tracker("sift", first)
    with pytest.raises(BackendError, match="bad options"):
        make_tracker("klt", first, window=5)
    with pytest.raises(BackendError, match="bad options"):
        make_tracker("geometry", first, lambda_chamfr=2.0)
    with pytest.raises(BackendError, match="no 'mode' option"):
        make_tracker("geometry", first, mode="geometry+")
    with pytest.raises(InputError, match="needs the simulator's ground_truth"):
        make_tracker("groundtruth", first)
    with pytest.raises(InputError, match="points.npy: missing"):
        make_tracker("groundtruth", first, ground_truth=tmp_path)
    with pytest.raises(BackendError, match="no checkpoint"):
        make_tracker("cotracker", first)
    online = make_tracker("static", first, POINTS)
    with pytest.raises(BackendError, match="online"):
        online.finish()


@pytest.mark.skipif(not os.environ.get("VFDATA_COTRACKER_CHECKPOINT"),
                    reason="needs the cotracker package and VFDATA_COTRACKER_CHECKPOINT=<scaled_offline.pth>")
def test_cotracker_collects_the_clip_and_finishes_with_its_own_tracks(scene):
    from vfdata.tracking import CoTrackerTracker

    frames, _ = scene
    checkpoint = os.environ["VFDATA_COTRACKER_CHECKPOINT"]
    tracker = make_tracker("cotracker", inputs(frames[0], 0), POINTS, 3, checkpoint=checkpoint)
    assert tracker.offline
    with pytest.raises(BackendError, match="offline"):
        tracker.update(inputs(frames[1], 1))
    for f in range(1, FRAMES):
        tracker.collect(inputs(frames[f], f))
    points, visible = tracker.finish()
    own = CoTrackerTracker(frames[0]["cloud"], CAMERA, checkpoint, num_points=POINTS, seed=3)
    want_points, want_visible = own.track(np.stack([fr["image"][..., ::-1] for fr in frames]),
                                          np.stack([fr["depth"] for fr in frames]),
                                          np.stack([fr["mask"] for fr in frames]))
    np.testing.assert_allclose(points, want_points)
    np.testing.assert_array_equal(visible, want_visible)
