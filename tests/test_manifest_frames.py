"""Splits in time: manifest entries naming frame ranges of one recording, with a clip's guard gap."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from vfdata.errors import InputError
from vfdata.manifest import check_guard_gaps, load_manifest


def _manifest(tmp_path, ranges, mcap="rec.mcap"):
    recordings = [{"id": f"r_{split}", "split": split, "mcap": mcap, "processed": "rec.processed.mcap",
                   **({"frames": r} if r is not None else {})} for split, r in ranges]
    path = tmp_path / "m.manifest.yaml"
    path.write_text(yaml.safe_dump({"name": "m", "root": ".", "recordings": recordings}))
    return load_manifest(path)


def test_a_temporal_split_with_guard_gaps_passes_and_keeps_its_ranges(tmp_path):
    manifest = _manifest(tmp_path, [("train", [0, 700]), ("val", [716, 800]), ("test", [816, 1000])])
    check_guard_gaps(manifest, 16)
    assert [e.frames for e in manifest] == [(0, 700), (716, 800), (816, 1000)]
    assert len({e.processed for e in manifest}) == 1


@pytest.mark.parametrize(("ranges", "says"), [
    ([("train", [0, 700]), ("val", [710, 800])], "'r_train' (train, frames [0, 700]) and 'r_val' (val, frames "
                                                 "[710, 800]) of rec.mcap are 10 frames apart"),
    ([("train", [0, 700]), ("test", [600, 800])], "overlap"),
    ([("train", [0, 700]), ("val", None)], "'r_train' and 'r_val' share rec.mcap: each needs frames"),
])
def test_splits_of_one_recording_closer_than_a_clip_are_refused(tmp_path, ranges, says):
    manifest = _manifest(tmp_path, ranges)
    with pytest.raises(InputError) as err:
        check_guard_gaps(manifest, 16)
    assert str(err.value).startswith(str(manifest.path)) and says in str(err.value)
    assert "guard gap of a clip's length (16 frames)" in str(err.value) or "each needs" in str(err.value)


def test_separate_recordings_need_no_frames(tmp_path):
    path = tmp_path / "m.manifest.yaml"
    path.write_text(yaml.safe_dump({"recordings": [{"id": "a", "split": "train"}, {"id": "b", "split": "val"}]}))
    check_guard_gaps(load_manifest(path), 16)


def test_the_datamodule_checks_the_gap_with_its_clip_length(tmp_path):
    from vfdata.clips import ClipSpec
    from vfdata.clips.datamodule import ForceDataModule

    manifest = _manifest(tmp_path, [("train", [0, 700]), ("val", [716, 800])])
    ForceDataModule(manifest.path, spec=ClipSpec(clip_frames=16))
    with pytest.raises(InputError, match=r"guard gap of a clip's length \(32 frames\)"):
        ForceDataModule(manifest.path, spec=ClipSpec(clip_frames=32))


def test_random_split_of_the_datamodule_is_a_seeded_partition(tmp_path):
    from vfdata.clips import ClipSpec
    from vfdata.clips.datamodule import ForceDataModule, random_parts

    parts = random_parts(100, 0.2)
    assert [len(parts[s]) for s in ("train", "val", "test")] == [72, 8, 20]
    assert sorted(np.concatenate(list(parts.values())).tolist()) == list(range(100))
    assert all((random_parts(100, 0.2)[s] == parts[s]).all() for s in parts)
    manifest = _manifest(tmp_path, [("train", [0, 700]), ("val", [716, 800])])
    assert ForceDataModule(manifest.path, spec=ClipSpec(), random_split=0.2).hparams["random_split"] == 0.2
    with pytest.raises(InputError, match="random_split"):
        ForceDataModule(manifest.path, spec=ClipSpec(), random_split=1.0)
