"""LeRobot datasets against LeRobot itself (slow): our export loads in LeRobot's own `LeRobotDataset`
and its `delta_timestamps` windows return the force we stored (v3.0 directly, v2.1 through LeRobot's
own v2.1 -> v3.0 converter); a dataset made by LeRobot's API from simulated recordings converts,
processes and trains (`vfdata experiment --variants ridge`) with no hand edits; the simulator's mini
dataset goes out to LeRobot and back and trains.

LeRobot pins its own torch, so it runs in its own virtual environment, as a separate process:
`python3 -m venv ../lerobot-venv && ../lerobot-venv/bin/pip install lerobot` (or name its Python with
VISIONFORCE_LEROBOT_PYTHON). Those tests are skipped without it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vfdata.cli import main
from vfdata.conversion.options import ConvertOptions
from vfdata.conversion.raw_folder import convert_raw_folder
from vfdata.lerobot.episodes import frame_rate
from vfdata.lerobot.export import ExportOptions, export_lerobot
from vfdata.lerobot.video import psnr_db
from vfdata.manifest import load_manifest
from vfdata.recording import Recording
from vfdata.sim.synthesize import synthesize

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[1]
LEROBOT_PYTHON = Path(os.environ.get("VISIONFORCE_LEROBOT_PYTHON", REPO.parent / "lerobot-venv" / "bin" / "python"))
needs_lerobot = pytest.mark.skipif(not LEROBOT_PYTHON.is_file(), reason=f"no LeRobot environment at {LEROBOT_PYTHON} "
                                   "(python3 -m venv ../lerobot-venv && ../lerobot-venv/bin/pip install lerobot)")
SCRIPTS = Path(__file__).parent / "lerobot_scripts"
FRAMES = 150  # of each mini recording: enough for the ridge's clips and lags


def lerobot(*args: str, cwd: Path) -> str:
    """Run LeRobot's Python; its output, or the test fails with it."""
    done = subprocess.run([str(LEROBOT_PYTHON), *args], cwd=cwd, capture_output=True, text=True, timeout=1200,
                          env={**os.environ, "HF_HUB_OFFLINE": "1", "PYTHONPATH": ""})
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return done.stdout


@pytest.fixture(scope="module")
def mini(tmp_path_factory) -> Path:
    """The simulator's mini dataset, FRAMES frames a recording, as raw folders and recording MCAPs."""
    root = tmp_path_factory.mktemp("mini")
    synthesize("mini", root, frames=FRAMES, progress=False)
    for raw in sorted(p for p in root.iterdir() if p.is_dir()):
        convert_raw_folder(raw, root / f"{raw.name}.mcap", options=ConvertOptions(progress=False))
    return root


def recordings(mini: Path) -> list[Path]:
    return sorted(mini.glob("mini_00?.mcap"))


@needs_lerobot
@pytest.mark.parametrize("version", ["v3.0", "v2.1"])
def test_lerobot_loads_our_export_and_its_windows_return_our_force(tmp_path, mini, version):
    (tmp_path / "local").mkdir()
    out = export_lerobot(recordings(mini), tmp_path / "local" / "export", options=ExportOptions(version=version,
                                                                                                progress=False))
    if version == "v2.1":  # LeRobot reads v2.1 through its own converter (in place, keeping the v2.1 copy)
        lerobot("-m", "lerobot.datasets.v30.convert_dataset_v21_to_v30", "--repo-id=local/export",
                f"--root={tmp_path}", "--push-to-hub=false", cwd=tmp_path)
    lerobot(str(SCRIPTS / "read_export.py"), str(out), str(tmp_path / "read.npz"), cwd=tmp_path)
    read = np.load(tmp_path / "read.npz")
    # Episodes in split order: mini_000 train, mini_001 val, mini_002 test.
    recs = [Recording.open(p) for p in recordings(mini)]
    frame_ns = np.concatenate([r.frame_times_ns for r in recs])
    episode = np.concatenate([np.full(r.num_frames, e) for e, r in enumerate(recs)])
    force = np.concatenate([r.force_at(r.frame_times_ns, max_gap_ns=10**8) for r in recs])
    assert int(read["total"]) == len(frame_ns) and int(read["fps"]) == 30
    assert np.array_equal(read["stamp_ns"], frame_ns) and np.array_equal(read["episode"], episode)
    for i, got, pad in zip(read["window_index"], read["window_force"], read["window_pad"], strict=True):
        want = [max(i + d, int(np.argmax(episode == episode[i]))) for d in (-2, -1, 0)]
        np.testing.assert_allclose(got, force[want], rtol=1e-6, atol=1e-7)
        assert pad.tolist() == [i + d < int(np.argmax(episode == episode[i])) for d in (-2, -1, 0)]
    first = recs[0]
    samples, counts = read["samples"][: first.num_frames], read["counts"][: first.num_frames]
    got = np.concatenate([s[:c] for s, c in zip(samples, counts, strict=True)])
    lo, hi = first.frame_times_ns[0] - round(1e9 / 30), first.frame_times_ns[-1]
    span = (first.force.times_ns > lo) & (first.force.times_ns <= hi)
    np.testing.assert_allclose(got, first.force.wrench[span], rtol=1e-6, atol=1e-7)  # LeRobot hands out float32
    last = recs[-1].frame(recs[-1].num_frames - 1).left[..., ::-1]
    assert psnr_db(read["last_left"].transpose(1, 2, 0), last) > 33
    for r in recs:
        r.close()


@needs_lerobot
def test_a_dataset_made_by_lerobot_converts_processes_and_trains(tmp_path, mini, capsys):
    raws = [mini / f"mini_00{i}" for i in range(3)]
    lerobot(str(SCRIPTS / "make_dataset.py"), str(tmp_path / "made"), *(f"{r}:{s}" for r, s in
                                                                         zip(raws, ("train", "val", "test"),
                                                                             strict=True)), cwd=tmp_path)
    boxes = [json.dumps(_box(r)).strip("[]").replace(" ", "") for r in raws]
    assert main(["convert", str(tmp_path / "made"), str(tmp_path / "lab"), "--calibration",
                 str(raws[0] / "calibration.yaml"), "--topics", "pose=observation.state", "--quiet",
                 *(f"--meta={e}:prompt_box={b}" for e, b in enumerate(boxes)), "--meta", "2:orientation_deg=90"]) == 0
    manifest = tmp_path / "lab" / "made.manifest.yaml"
    entries = load_manifest(manifest).entries
    assert [(e.split, e.orientation_deg) for e in entries] == [("train", 0), ("val", 0), ("test", 90)]
    with Recording.open(entries[0].mcap) as got, Recording.open(mini / "mini_000.mcap") as original:
        assert got.num_frames == original.num_frames and frame_rate(got) == pytest.approx(30, rel=1e-3)
        want = original.force_at(original.frame_times_ns, max_gap_ns=10**8)
        # float32 in LeRobot, and the script interpolates on float64 epoch nanoseconds (256 ns steps)
        np.testing.assert_allclose(got.force.wrench, want, atol=1e-4)
        assert np.mean([psnr_db(got.frame(i).left, original.frame(i).left) for i in (0, 75, 149)]) > 33
    capsys.readouterr()
    assert main(["experiment", str(manifest), "--out", str(tmp_path / "results"), "--variants", "ridge",
                 "--seeds", "1"]) == 0
    metrics = json.loads(next((tmp_path / "results" / "runs" / "ridge").glob("seed*/metrics.json")).read_text())
    assert metrics["test_frames"] > 100 and np.isfinite(metrics["pooled"]["rmse"])
    assert "Table II" in capsys.readouterr().out


def test_mini_goes_out_to_lerobot_and_back_and_trains(tmp_path, mini, capsys):
    assert main(["export", "--lerobot", *map(str, recordings(mini)), str(tmp_path / "mini_lerobot"), "--quiet"]) == 0
    assert main(["convert", str(tmp_path / "mini_lerobot"), str(tmp_path / "back"), "--quiet"]) == 0
    manifest = tmp_path / "back" / "mini_lerobot.manifest.yaml"
    entries = load_manifest(manifest).entries
    assert [(e.id, e.split, e.orientation_deg) for e in entries] == [("mini_000", "train", 0), ("mini_001", "val", 0),
                                                                     ("mini_002", "test", 90)]
    for entry in entries:
        with Recording.open(entry.mcap) as back, Recording.open(mini / f"{entry.id}.mcap") as original:
            assert np.array_equal(back.frame_times_ns, original.frame_times_ns)
            assert back.metadata.extra["prompt_box"] == original.metadata.extra["prompt_box"]
    capsys.readouterr()
    assert main(["experiment", str(manifest), "--out", str(tmp_path / "results"), "--variants", "ridge",
                 "--seeds", "1"]) == 0
    assert "Table II" in capsys.readouterr().out


def _box(raw: Path) -> list[int]:
    import yaml

    return yaml.safe_load((raw / "meta.yaml").read_text())["prompt_box"]


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-m", "slow", "-q"]))
