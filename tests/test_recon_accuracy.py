"""The issue's accuracy targets on the simulator's `mini` recordings (slow: synthesizes them)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from recon_fixtures import load_sim_frames, make_sim_recording

from vfdata.calibration import StereoCalibration
from vfdata.recon import (
    Prompt,
    make_depth_estimator,
    make_segmenter,
    mask_iou,
    tissue_cloud,
    up_in_camera,
)
from vfdata.recon.tissue_frame import tissue_frame

FRAMES = 20


@pytest.mark.slow
def test_reconstruction_meets_the_targets_on_the_simulator(tmp_path):
    ious, rels, z_errors, wide = [], [], [], []
    for index in range(3):  # train, val and test recordings
        rec = make_sim_recording(tmp_path, index=index, frames=FRAMES)
        data = load_sim_frames(rec, FRAMES)
        stereo = StereoCalibration.load(rec / "calibration.yaml").rectified
        depth_est = make_depth_estimator("sgbm", min_disparity=8, max_disparity=64)
        segmenter = make_segmenter("colortrack")
        prompt = Prompt.from_box(data["prompt_box"])
        for i in range(FRAMES):
            depth = depth_est.depth_mm(data["left"][i], data["right"][i], stereo.left, stereo.baseline_mm)
            if i == 0:
                mask = segmenter.start(data["left"][i], prompt, depth)
                first_depth, first_mask = depth, mask
            else:
                mask = segmenter.track(data["left"][i], depth)
            truth_mask, truth_depth = data["mask"][i], data["depth"][i]
            ious.append(mask_iou(mask, truth_mask))
            inside = truth_mask & np.isfinite(truth_depth)
            rels.append(np.nanmean(np.abs(depth[inside] - truth_depth[inside]) / truth_depth[inside]))
        pose = np.loadtxt(rec / "ecm_pose.csv", delimiter=",", skiprows=1, ndmin=2)[0]
        up = up_in_camera(pose[4:8])
        # the frame as `vfdata process` decides it (the paper's search among the product's fits and cues)
        frame = tissue_frame(data["left"][0], first_mask, first_depth,
                             tissue_cloud(first_depth, first_mask, stereo.left), stereo.left, up)
        truth_z = np.array(json.loads((rec / "ground_truth" / "object_frame.json").read_text())["rotation"])[
            :, 2
        ]
        z_errors.append(np.degrees(np.arccos(min(1.0, abs(float(frame.z_axis @ truth_z))))))
        wide.append(float(frame.z_axis @ truth_z) > 0)
        projected = up - (up @ frame.z_axis) * frame.z_axis
        assert np.degrees(np.arccos(min(1.0, frame.x_axis @ projected / np.linalg.norm(projected)))) < 3.0
    assert np.mean(ious) >= 0.9, np.round(ious, 3)
    assert np.mean(rels) <= 0.03
    assert np.median(z_errors) <= 3.0, z_errors
    assert all(wide), z_errors
