"""How a tissue hangs (`vfdata.tissue_lean`): the lean below level of a processed recording's object frame,
and the experiment's note on recordings whose tissue hangs unlike the training tissues."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder
from vfdata.manifest import load_manifest
from vfdata.processing import ProcessOptions, process_recording
from vfdata.recording.derived import DerivedRecording
from vfdata.sim import synthesize
from vfdata.tissue_lean import (
    beyond_range,
    lean_deg,
    lean_markdown,
    lean_report,
    lean_warnings,
    read_lean,
    unlike_training,
)
from vfmodels.experiment.report import write_lean

UP = np.array([0.0, -1.0, 0.0])  # a camera looking level: up is -y
NAMES = ("mini_000", "mini_001", "mini_002", "mini_003", "mini_004")
SPLITS = {"mini_000": "train", "mini_001": "val", "mini_002": "test", "mini_003": "train", "mini_004": "train"}


def along(down_deg: float) -> np.ndarray:
    """A unit Z running along the camera's x and `down_deg` below level."""
    a = np.radians(down_deg)
    return np.array([np.cos(a), np.sin(a), 0.0])


@pytest.mark.parametrize("down", [0.0, 6.0, -3.0, 45.0])
def test_the_lean_is_the_angle_below_level(down):
    assert lean_deg(along(down), UP) == pytest.approx(down, abs=1e-9)
    assert lean_deg(along(down) * 3.0, UP * 2.0) == pytest.approx(down, abs=1e-9)  # any lengths


def test_beyond_the_training_range_only_past_the_margin():
    training = [4.0, 5.5, 7.0]
    assert beyond_range(5.0, training) == 0.0
    assert beyond_range(7.9, training) == 0.0 and beyond_range(3.1, training) == 0.0  # within 1 deg (MARGIN_DEG)
    assert beyond_range(8.5, training) == pytest.approx(1.5)   # softer: hangs lower
    assert beyond_range(2.5, training) == pytest.approx(-1.5)  # stiffer: hangs higher
    assert beyond_range(7.4, training, margin=0.0) == pytest.approx(0.4)


def test_the_report_ranges_over_the_training_recordings_kept():
    leans = {"a": ("train", 4.0), "b": ("train", 6.0), "d": ("train", 5.0), "c": ("train", 12.0), "v": ("val", 7.5),
             "t1": ("test", 5.0), "t2": ("test", 2.0), "t3": ("test", None), "t4": ("test", 19.0)}
    report = lean_report(leans, doubtful={"c", "t4"})  # judged doubtful: their frames, so leans, may be wrong
    assert report["training_deg"] == [4.0, 6.0] and report["training_recordings"] == 3
    rows = {r["id"]: r for r in report["recordings"]}
    assert set(rows) == {"v", "t1", "t2"}  # no lean (no gravity) or doubtful: not judged
    assert rows["v"]["beyond_deg"] == pytest.approx(1.5) and rows["t1"]["beyond_deg"] == 0.0
    warnings = lean_warnings(report)
    assert len(warnings) == 2
    assert warnings[0] == "v (val) hangs 7.5 deg below level, outside the training tissues' 4.0 to 6.0 deg below level"
    assert warnings[1].startswith("t2 (test) hangs 2.0 deg below level, outside")
    text = lean_markdown(report)
    assert "| t2 | test | 2.0 | -2.0 |" in text and "| t1 | test | 5.0 | |" in text


def test_without_gravity_or_with_fewer_than_three_tissues_there_is_no_range_and_no_warning():
    report = lean_report({"a": ("train", None), "b": ("train", None), "c": ("train", None), "t": ("test", 3.0)})
    assert report["training_deg"] is None and report["recordings"] == [] and lean_warnings(report) == []
    # two training tissues are two draws of the spread between tissues: no range to judge by
    report = lean_report({"a": ("train", 4.0), "b": ("train", 5.0), "t": ("test", 9.0)})
    assert report["training_deg"] is None and lean_warnings(report) == []


def test_a_tissue_above_level_is_said_so():
    assert unlike_training(-1.74, [3.0, 5.0]).startswith("hangs 1.7 deg above level, outside the training tissues'")
    assert unlike_training(4.2, [3.0, 5.0]) is None


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A `mini` dataset with three training tissues (mini_000, mini_003, mini_004; val mini_001, test mini_002),
    processed, 4 frames each."""
    root = tmp_path_factory.mktemp("sim")
    synthesize("mini", root, seed=3, frames=4, progress=False, split_recordings={"train": 3})
    for name in NAMES:
        mcap = convert_raw_folder(root / name, root / f"{name}.mcap", options=ConvertOptions(progress=False))
        process_recording(mcap, options=ProcessOptions(progress=False, tracker="none"))
    return root


def test_process_writes_the_lean_against_gravity(dataset):
    processed = dataset / "mini_000.processed.mcap"
    with DerivedRecording.open(processed) as derived:
        lean, z = derived.meta.tissue_lean_deg, derived.object_frame.z_axis
    truth = json.loads((dataset / "mini_000" / "ground_truth" / "object_frame.json").read_text())
    # the simulator's clamp is level and its object frame's X is gravity-up: the lean is Z's angle below it
    assert lean == pytest.approx(lean_deg(z, np.asarray(truth["rotation"])[:, 0]), abs=0.01)
    assert 0.0 < lean < 15.0  # the tissue hangs from its clamp
    assert read_lean(processed, dataset / "mini_000.mcap") == pytest.approx(lean)


def test_files_from_before_get_the_lean_from_the_raw_recordings_gravity(dataset, tmp_path):
    """A derived file without the key (written before 2026-12-06) gets the same lean from its object frame
    and the raw recording's ECM pose."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    processed, old = dataset / "mini_000.processed.mcap", tmp_path / "old.processed.mcap"
    with open(processed, "rb") as src, open(old, "wb") as dst:
        reader, writer = make_reader(src), Writer(dst)
        summary = reader.get_summary()
        writer.start(profile=reader.get_header().profile, library="test")
        schemas = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in summary.schemas.items()}
        channels = {cid: writer.register_channel(c.topic, c.message_encoding, schemas.get(c.schema_id, 0),
                                                 c.metadata) for cid, c in summary.channels.items()}
        for _, channel, message in reader.iter_messages():
            writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time)
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, {k: v for k, v in record.metadata.items() if k != "tissue_lean_deg"})
        writer.finish()
    with DerivedRecording.open(old) as derived:
        assert derived.meta.tissue_lean_deg is None
    with DerivedRecording.open(processed) as derived:
        assert read_lean(old, dataset / "mini_000.mcap") == pytest.approx(derived.meta.tissue_lean_deg, abs=0.01)


def test_the_experiment_report_names_a_tissue_unlike_training(dataset, tmp_path):
    manifest = tmp_path / "m.yaml"
    manifest.write_text("name: m\nrecordings:\n" + "".join(
        f"  - {{id: {name}, mcap: {dataset / name}.mcap, split: {SPLITS[name]}}}\n" for name in NAMES))
    entries = list(load_manifest(manifest).entries)
    leans = {e.id: read_lean(dataset / f"{e.id}.processed.mcap", e.mcap) for e in entries}
    trained = [leans[n] for n in NAMES if SPLITS[n] == "train"]
    paths = write_lean(tmp_path, entries, ["geometry"], [])
    report = json.loads((tmp_path / "lean.json").read_text())
    assert paths == {"lean.md": tmp_path / "lean.md"}
    assert report["training_deg"] == [round(min(trained), 2), round(max(trained), 2)]
    rows = {r["id"]: r for r in report["recordings"]}
    assert set(rows) == {"mini_001", "mini_002"}
    named = []
    for name in rows:
        assert rows[name]["lean_deg"] == pytest.approx(leans[name], abs=0.01)
        assert rows[name]["beyond_deg"] == pytest.approx(beyond_range(leans[name], trained), abs=0.01)
        if beyond_range(leans[name], trained):
            named.append(name)
    text = (tmp_path / "lean.md").read_text()
    assert [line[2:10] for line in text.splitlines() if line.startswith("- ")] == named
    # a training recording doubtful: two left, no range to judge by, no report
    assert write_lean(tmp_path / "none", entries, ["geometry"], [{"id": "mini_000", "left_out": True}]) == {}


def test_a_checkpoint_remembers_how_the_training_tissues_hang(dataset, tmp_path):
    """The data module's state (saved in every checkpoint, read by `vfdata predict`) holds the range of the
    training recordings' leans, those judged doubtful left out."""
    from vfdata.clips.datamodule import ForceDataModule

    manifest = tmp_path / "m.yaml"
    manifest.write_text(f"name: m\nroot: {dataset}\nrecordings:\n" + "".join(
        f"  - {{id: {name}, split: {SPLITS[name]}}}\n" for name in NAMES))
    leans = [read_lean(dataset / f"{name}.processed.mcap", dataset / f"{name}.mcap")
             for name in NAMES if SPLITS[name] == "train"]
    state = ForceDataModule.from_manifest(manifest, progress=False).state_dict()
    assert state["tissue_lean_deg"] == [round(min(leans), 2), round(max(leans), 2)]
