"""The simulator upper-bound variants of the experiment runner: `groundtruth` and
`camera_frame_groundtruth` read the simulator's true tracks (tracker `groundtruth`) with the proposed
and the camera-frame configs; they run only when named, and get their own rows and claim."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from test_experiment import _fake_runs, write_manifest

from vfmodels.experiment import report, runner
from vfmodels.experiment.variants import ALL_VARIANTS, TRACKER_SUFFIX
from vfmodels.reports import tables


def test_ground_truth_variants_are_named_only():
    default = [v.name for v in runner.ExperimentOptions().chosen()]
    assert "groundtruth" not in default and "camera_frame_groundtruth" not in default
    chosen = runner.ExperimentOptions(variants=["groundtruth", "camera_frame_groundtruth"]).chosen()
    assert [v.tracker for v in chosen] == ["groundtruth", "groundtruth"]


@pytest.mark.parametrize("name, twin, frame", [("groundtruth", "proposed", "object"),
                                                ("camera_frame_groundtruth", "camera_frame", "camera")])
def test_ground_truth_variant_is_its_twin_on_true_tracks(name, twin, frame):
    """Same model and inputs as the twin variant; only the tracks differ, so the pair isolates tracking."""
    variant, other = ALL_VARIANTS[name], ALL_VARIANTS[twin]
    assert variant.config == other.config and variant.tracker == "groundtruth" != other.tracker
    config = yaml.safe_load((runner.CONFIGS / variant.config).read_text())
    assert config["data"]["init_args"]["spec"]["frame"] == frame
    assert config["data"]["init_args"]["spec"]["input"] == "tracks"
    assert TRACKER_SUFFIX["groundtruth"] == ".gt.mcap"


def test_ground_truth_rows_and_claim_in_the_reports(tmp_path):
    manifest = write_manifest(tmp_path)
    out = tmp_path / "results"
    _fake_runs(out, {"proposed": 0.3, "camera_frame": 0.2, "groundtruth": 0.05, "camera_frame_groundtruth": 0.25})
    paths = report.write_reports(out, manifest)
    table2 = paths["table2.md"].read_text()
    assert "Ground-truth tracks (simulator upper bound)" in table2 and "Camera frame, ground-truth tracks" in table2
    assert "Ground-truth" not in paths["table1.md"].read_text()
    # Rows in the order of the grid: the paper's variants first, then the upper bounds.
    assert table2.index("Proposed") < table2.index("Ground-truth tracks") < table2.index("Camera frame, ground")
    claims = json.loads(paths["claims"].read_text())
    assert claims["object_frame_halves_rmse"]["holds"] is False  # 0.3 vs 0.2
    gt = claims["object_frame_halves_rmse_groundtruth"]
    assert gt["holds"] is True
    runs = report.load_runs(out)
    rmse = {n: tables.aggregate_seeds(runs[n])["value"]["rmse"]
            for n in ("groundtruth", "camera_frame_groundtruth")}
    assert gt["reduction"] == pytest.approx(1 - rmse["groundtruth"] / rmse["camera_frame_groundtruth"])


@pytest.mark.slow
def test_ground_truth_variants_end_to_end(tmp_path):
    """Synthesis -> processing with the ground-truth tracker -> both variants trained and tested: the
    true tracks are exact (Table III error 0) and the object frame is the processing's estimate."""
    from vfdata.recording.derived import read_tracks
    from vfdata.sim import synthesize

    manifest = synthesize("mini", tmp_path / "data", seed=0, workers=2, progress=False, frames=40)
    options = runner.ExperimentOptions(seeds=1, epochs=1, variants=["groundtruth", "camera_frame_groundtruth"],
                                           workers=2, progress=False)
    result = runner.run_experiment(manifest, tmp_path / "results", options)
    processed = tmp_path / "data" / "mini_002.gt.mcap"
    assert processed.is_file() and not (tmp_path / "data" / "mini_002.processed.mcap").exists()
    for variant in ("groundtruth", "camera_frame_groundtruth"):
        metrics = json.loads((tmp_path / "results" / "runs" / variant / "seed0" / "metrics.json").read_text())
        assert metrics["tracker"] == "groundtruth" and metrics["test_frames"] > 0
        assert np.isfinite(metrics["pooled"]["rmse"])
    table3 = result.reports["table3.md"].read_text()
    assert "Ground truth" in table3
    per_recording = json.loads((tmp_path / "results" / "tracking_per_recording.json").read_text())
    assert per_recording["groundtruth"]["mini_002"]["error"]["full_p95_mm"] < 1e-3
    # The tracks follow the material: they move between the first and the last frame.
    tracks = read_tracks(processed)
    assert np.abs(tracks.points_object_mm[-1] - tracks.points_object_mm[0]).max() > 0.1
