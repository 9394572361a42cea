"""The splits' forces before training: force beyond training's range and coupled components are
found, said in one line each, and written beside the results; the labels are read per frame range."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from tests.rgbd_fixtures import make_rgbd
from vfdata.conversion.options import ConvertOptions
from vfdata.conversion.raw_rgbd import convert_rgbd_folder
from vfdata.manifest import load_manifest
from vfdata.recording import Recording
from vfdata.split_forces import manifest_forces, split_warnings, summarise, write_split_report


def _forces(seed: int = 0):
    rng = np.random.default_rng(seed)
    train = rng.uniform(-1, 1, size=(500, 3)) * [2.0, 2.0, 40.0]
    test = rng.uniform(-1, 1, size=(100, 3)) * [2.0, 2.0, 40.0]
    return train, test


def test_a_test_inside_training_and_independent_components_raise_nothing():
    train, test = _forces()
    summary = summarise({"train": train, "test": test})
    assert summary["train"]["frames"] == 500 and "beyond_training" not in summary["train"]
    assert summary["test"]["beyond_training"] == 0.0
    assert all(abs(v) < 0.2 for v in summary["train"]["coupling"].values())
    assert split_warnings(summary) == []


def test_force_beyond_training_is_counted_per_component_and_said():
    train, test = _forces()
    test[:20, 2] = -105.0  # a press deeper than any in training
    test[20:25, 0] = 3.0
    summary = summarise({"train": train, "test": test})
    assert summary["test"]["beyond_training"] == pytest.approx(0.25)
    assert summary["test"]["beyond_training_per_component"] == {"fx": 0.05, "fy": 0.0, "fz": 0.2}
    (line,) = split_warnings(summary)
    assert line.startswith("test: 25% of its 100 frames have force beyond the training range by more than a tenth")
    assert "Fz down to -105.0 N (training " in line and "Fx up to 3.0 N" in line and "Fy" not in line
    test[:, :] = train[:100]
    test[:3, 1] = train[:, 1].max() + 1.0  # three frames in a hundred: under the 5% worth a word
    assert summarise({"train": train, "test": test})["test"]["beyond_training"] == pytest.approx(0.03)
    assert split_warnings(summarise({"train": train, "test": test})) == []
    test[:50, 1] = train[:, 1].max() + 0.3  # within a tenth of training's 4 N range: not beyond
    assert summarise({"train": train, "test": test})["test"]["beyond_training"] == 0.0


def test_coupled_training_components_are_said_and_a_constant_one_has_no_correlation():
    train, test = _forces()
    train[:, 1] = 0.9 * train[:, 0] + 0.05 * np.random.default_rng(1).normal(size=500)
    summary = summarise({"train": train, "test": test})
    assert summary["train"]["coupling"]["fx_fy"] > 0.95
    assert any(line.startswith("train: components move together (Fx-Fy +1.00)") for line in split_warnings(summary))
    train[:, 2] = 0.0
    assert summarise({"train": train})["train"]["coupling"]["fx_fz"] is None


def test_the_report_is_json_and_a_table_with_the_warnings(tmp_path):
    train, test = _forces()
    test[:10, 2] = -80.0
    paths = write_split_report(tmp_path / "out", summarise({"train": train, "val": train[:50], "test": test}))
    assert [p.name for p in paths] == ["splits.json", "splits.md"]
    assert json.loads(paths[0].read_text())["test"]["beyond_training"] == pytest.approx(0.1)
    text = paths[1].read_text()
    assert "| test | 100 |" in text and "| 10% |" in text and "- test: 10% of its 100 frames" in text


def test_labels_are_read_per_frame_range_of_each_entry(tmp_path):
    raw = make_rgbd(tmp_path / "raw", n=12)
    mcap = convert_rgbd_folder(raw, tmp_path / "rec.mcap", options=ConvertOptions(progress=False))
    recordings = [{"id": "a", "split": "train", "mcap": "rec.mcap", "frames": [0, 8]},
                  {"id": "b", "split": "test", "mcap": "rec.mcap", "frames": [8, 12]}]
    path = tmp_path / "m.manifest.yaml"
    path.write_text(yaml.safe_dump({"name": "m", "root": ".", "recordings": recordings}))
    forces = manifest_forces(load_manifest(path))
    with Recording.open(mcap) as rec:
        every = rec.force_at(rec.frame_times_ns)[:, :3]
    np.testing.assert_array_equal(forces["train"], every[:8])
    np.testing.assert_array_equal(forces["test"], every[8:])
