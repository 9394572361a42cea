"""The real recording end to end (slow, about 2 minutes on two CPU cores): the README's commands on
../shared/data/gao2018/rgbd as published, with the committed datasets/gao2018/ cameras and metadata:
convert, check, process, the experiment on the temporal split, the study, and prediction without the
sensor (offline and streamed)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
RAW = (REPO / ".." / "shared" / "data" / "gao2018" / "rgbd").resolve()

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800),
              pytest.mark.skipif(not RAW.is_dir(), reason=f"{RAW} is not here (the Gao et al. 2018 Kinect "
                                                          "recording: ../shared/data/gao2018/README.md)")]


def _run(*args: str) -> str:
    done = subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=REPO)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def test_the_real_recording_converts_processes_and_trains_as_published(tmp_path):
    before = sorted((p.name, p.stat().st_size) for p in RAW.rglob("*"))
    mcap = tmp_path / "gao2018_1_1.mcap"
    _run("-m", "vfdata", "convert", str(RAW), str(mcap), "--quiet",
         "--calibration", "datasets/gao2018/rgbd_calibration.yaml", "--meta", "datasets/gao2018/meta.yaml")
    assert _run("-m", "vfdata", "check", str(mcap)).strip().endswith(": ok")
    info = _run("-m", "vfdata", "info", str(mcap))
    assert "/camera/depth/image" in info and "layout: RGB-D (depth-to-colour transform unknown)" in info
    _run("-m", "vfdata", "process", str(mcap), "--quiet")
    # the committed manifest, its outputs moved under tmp_path (its inputs stay where they are)
    manifest = yaml.safe_load((REPO / "datasets" / "gao2018.manifest.yaml").read_text())
    root = (REPO / "datasets" / manifest["root"]).resolve()
    for item in manifest["recordings"]:
        for key in ("raw", "calibration", "meta"):
            item[key] = str((root / item[key]).resolve())
    manifest["root"] = str(tmp_path)
    path = tmp_path / "gao2018.manifest.yaml"
    path.write_text(yaml.safe_dump(manifest))
    out = tmp_path / "results"
    _run("-m", "vfdata", "experiment", str(path), "--out", str(out), "--variants", "visionforce", "ridge",
         "--seeds", "1", "--epochs", "1", "--quiet")
    metrics = json.loads((out / "runs" / "visionforce" / "seed0" / "metrics.json").read_text())
    assert metrics["test_frames"] == 184 and metrics["pooled"]["rmse_fz"] > 0
    assert "VisionForce (deformation tokens, flat tissue: no symmetries)" in (out / "table1_force.md").read_text()
    splits = json.loads((out / "splits.json").read_text())  # said before training: 18 of 184 beyond
    assert splits["test"]["frames"] == 184 and splits["test"]["beyond_training"] == pytest.approx(18 / 184)
    _run("-m", "vfmodels.experiment.real_study", str(path), "--out", str(out), "--tracker-options",
         '{"lambda_anchor": 1.0}')
    study = json.loads((out / "study.json").read_text())
    assert set(study["temporal"]) >= {"visionforce", "constant", "ridge_depth_change", "ridge_masked_depth"}
    assert study["tracking"]["peaks"] and (out / "force_time.png").is_file() and (out / "tracks_peak.png").is_file()
    # the recording's own facts (no training involved): pulls look alike in both stretches, presses do not
    agree = study["stretch_responses"]["map_agreement"]
    assert agree["fx"] > 0.6 and agree["fy"] > 0.5 and agree["fz"] < 0.3 and (out / "force_maps.png").is_file()
    derived = _run("-m", "vfdata", "info", str(tmp_path / "gao2018_1_1.processed.mcap"))
    assert "object_frame_kind=board_plane" in derived and "depth=sensor" in derived
    # the trained model without the sensor: offline and frame by frame (across the Kinect's dropped
    # frames at 132 and 221) give the same forces, in the depth camera's tf tree
    from vfdata.recording import Recording, layout
    from vfdata.recording.derived import read_force_estimate

    ckpt = str(out / "runs" / "visionforce" / "seed0")
    _run("-m", "vfdata", "predict", str(mcap), "--ckpt", ckpt, "--out", str(tmp_path / "offline"), "--no-video",
         "--max-frames", "240", "--quiet")
    _run("-m", "vfdata", "predict", str(mcap), "--ckpt", ckpt, "--out", str(tmp_path / "stream"), "--stream",
         "--max-frames", "240", "--quiet")
    offline, stream = (read_force_estimate(tmp_path / run / "gao2018_1_1.force.mcap") for run in ("offline", "stream"))
    assert len(offline[0]) == 240 and (offline[0] == stream[0]).all()
    assert abs(offline[1] - stream[1]).max() < 1e-3
    with Recording.open(tmp_path / "stream" / "gao2018_1_1.force.mcap") as rec:
        assert next(rec.messages(layout.TF_STATIC))[1].transforms[0].frame_id == layout.DEPTH_FRAME
    assert sorted((p.name, p.stat().st_size) for p in RAW.rglob("*")) == before
