"""The experiment runner: manifests, per-tracker manifests, clip de-duplication, resumption, claims,
and the report step on run folders with known predictions."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from tests.rgbd_fixtures import make_rgbd
from vfdata.clips.tokens import latest_clip_frames
from vfdata.conversion.options import ConvertOptions
from vfdata.conversion.raw_rgbd import convert_rgbd_folder
from vfdata.errors import InputError, VisionForceError
from vfdata.manifest import load_manifest
from vfdata.recording import Recording
from vfmodels.experiment import report, runner
from vfmodels.experiment.prepare import any_depth_only, derived_path, prepare
from vfmodels.experiment.report import doubtful_markdown, validation_recordings
from vfmodels.experiment.ridge_run import config_spec
from vfmodels.experiment.runner import CONFIGS
from vfmodels.experiment.variants import ALL_VARIANTS, PAPER_VARIANTS, VISIONFORCE_TRACKER, for_depth_only
from vfmodels.reports import tables


def write_manifest(folder, recordings=None):
    recordings = recordings or [
        {"id": "a", "orientation_deg": 0, "split": "train"},
        {"id": "b", "orientation_deg": 0, "split": "val"},
        {"id": "c", "orientation_deg": 90, "split": "test", "mcap": "elsewhere/c.mcap"},
    ]
    path = folder / "datasets" / "toy.manifest.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump({"name": "toy", "root": "../data", "recordings": recordings}))
    return path


def test_read_manifest_resolves_paths_relative_to_the_manifest(tmp_path):
    manifest = load_manifest(write_manifest(tmp_path))
    entries = manifest.entries
    assert manifest.name == "toy" and [e.id for e in entries] == ["a", "b", "c"]
    assert entries[0].raw == (tmp_path / "data" / "a").resolve()
    assert entries[0].mcap == (tmp_path / "data" / "a.mcap").resolve()
    assert entries[2].mcap == (tmp_path / "data" / "elsewhere" / "c.mcap").resolve()
    assert derived_path(entries[0], "geometry").name == "a.processed.mcap"
    assert derived_path(entries[0], "klt").name == "a.klt.mcap"
    assert entries[2].orientation_deg == 90.0


@pytest.mark.parametrize("content, problem", [
    ("recordings: []", "non-empty"),
    ("recordings: [{id: a, split: holdout}]", "split"),
    ("recordings: [: bad", "YAML"),
])
def test_bad_manifests_are_clear_errors(tmp_path, content, problem):
    path = tmp_path / "m.yaml"
    path.write_text(content)
    with pytest.raises(InputError, match=problem):
        load_manifest(path)
    with pytest.raises(InputError, match="not found"):
        load_manifest(tmp_path / "missing.yaml")


def test_tracker_manifest_points_at_the_tracker_files(tmp_path):
    manifest = load_manifest(write_manifest(tmp_path))
    path, doubtful = runner.tracker_manifest(manifest, "klt", tmp_path / "out" / "klt.manifest.yaml")
    assert doubtful == []  # no derived files yet: nothing judged
    copy = yaml.safe_load(path.read_text())
    assert copy["name"] == "toy-klt"
    assert [r["processed"] for r in copy["recordings"]] == [str(derived_path(e, "klt")) for e in manifest.entries]
    assert [r["split"] for r in copy["recordings"]] == ["train", "val", "test"]
    # Re-read through the same reader: absolute paths survive the move.
    again = load_manifest(path)
    assert [e.mcap for e in again] == [e.mcap for e in manifest.entries]


def _judged(entry, tracker: str, reasons: list[str]) -> None:
    """A derived file of `entry` whose verdict (vfdata.confidence) has these reasons."""
    from vfdata.confidence import Confidence
    from vfdata.recording.derived import DerivedWriter

    derived_path(entry, tracker).parent.mkdir(parents=True, exist_ok=True)
    with DerivedWriter(derived_path(entry, tracker), overwrite=True) as writer:
        writer.close({"stage": "process", "confidence": json.dumps(Confidence(reasons).to_dict())})


def test_doubtful_training_recordings_are_left_out_unless_kept(tmp_path):
    manifest = load_manifest(write_manifest(tmp_path))
    train, val, test = manifest.entries
    _judged(train, "klt", [])
    _judged(val, "klt", ["end"])
    _judged(test, "klt", ["axis"])
    path, doubtful = runner.tracker_manifest(manifest, "klt", tmp_path / "out" / "klt.manifest.yaml")
    assert [e.split for e in load_manifest(path).entries] == ["train", "test"]
    assert [(d["id"], d["reasons"], d["left_out"]) for d in doubtful] == [
        (val.id, ["end"], True), (test.id, ["axis"], False)]
    path, doubtful = runner.tracker_manifest(manifest, "klt", tmp_path / "out" / "kept.manifest.yaml",
                                             keep_doubtful=True)
    assert [e.split for e in load_manifest(path).entries] == ["train", "val", "test"]
    assert not any(d["left_out"] for d in doubtful)
    _judged(train, "klt", ["mask_edges"])
    with pytest.raises(InputError, match="--keep-doubtful"):
        runner.tracker_manifest(manifest, "klt", tmp_path / "out" / "none.manifest.yaml")
    md = doubtful_markdown(doubtful)
    assert f"| {val.id} | val | klt | end | no |" in md


def test_validation_recordings_counts_what_the_band_was_calibrated_on(tmp_path):
    from vfdata.manifest import ManifestEntry

    def entry(name, split, mcap, frames=None):
        return ManifestEntry(name, 0.0, split, tmp_path, tmp_path / mcap, tmp_path / f"{name}.d.mcap", frames)

    entries = [entry("t", "train", "t.mcap"), entry("v1", "val", "v1.mcap"), entry("v2", "val", "v2.mcap"),
               entry("v3a", "val", "v3.mcap", (0, 50)), entry("v3b", "val", "v3.mcap", (50, 99)),
               entry("x", "test", "x.mcap")]
    assert validation_recordings(entries, []) == 3  # two frame ranges of one recording: one tissue
    left = [{"id": "v1", "split": "val", "left_out": True}, {"id": "v2", "split": "val", "left_out": False}]
    assert validation_recordings(entries, left) == 2


def test_missing_recording_names_the_fix(tmp_path):
    entries = list(load_manifest(write_manifest(tmp_path)).entries)
    with pytest.raises(InputError, match="vfdata synth"):
        prepare(entries, ["geometry"], progress=False)


def test_every_variants_spec_is_valid_on_stereo_and_rgbd():
    """Each variant's config with its overrides (and its RGB-D twin's) makes a ClipSpec: an ablation that
    swaps visionforce's polar features for plain ones must also give r0 back in mm (radius)."""
    variants = list(ALL_VARIANTS.values())
    for v in variants + for_depth_only(variants):
        if "spec" in (yaml.safe_load((CONFIGS / v.config).read_text())["data"].get("init_args") or {}):
            config_spec(CONFIGS / v.config, v.overrides)


def test_rgbd_recordings_run_the_project_pipeline_on_depth_only_tracks(tmp_path):
    # On RGB-D the image trackers would follow the depth drawn as grey: VisionForce's own variants read
    # the geometry tracks there, and a variant that names its tracker keeps it.
    chosen = runner.ExperimentOptions(variants=["visionforce", "ridge", "visionforce_camera_frame", "klt",
                                                "visionforce@geometry", "proposed"]).chosen()
    assert [v.tracker for v in chosen][:3] == [VISIONFORCE_TRACKER] * 3 == ["klt"] * 3
    flat = for_depth_only(chosen)
    assert [v.tracker for v in flat] == ["geometry", "geometry", "geometry", "klt", "geometry", "geometry"]
    # A flat organ in the board frame has none of the tube's symmetries: VisionForce's configs train and
    # test without them there, and the ridge reads the same spec; the paper's configs are left as they are.
    for v in flat:
        if v.config.startswith("visionforce"):
            spec = config_spec(CONFIGS / v.config, v.overrides)
            assert not (spec.mirror_augment or spec.rotate_augment or spec.tilt_augment_deg), v.name
            assert "--model.symmetry_turns=0" in v.overrides
            assert "tube symmetries" not in v.label, v.label  # the tables say what ran
        else:
            assert v.overrides == ALL_VARIANTS[v.name].overrides
    src = make_rgbd(tmp_path / "rgbd", n=3)
    (tmp_path / "data").mkdir()
    convert_rgbd_folder(src, tmp_path / "data" / "a.mcap", options=ConvertOptions(progress=False, workers=1))
    manifest = write_manifest(tmp_path, [{"id": "a", "orientation_deg": 0, "split": "train"}])
    entries = list(load_manifest(manifest).entries)
    assert any_depth_only(entries)


def test_unknown_variant_is_an_error():
    with pytest.raises(VisionForceError, match="unknown variant"):
        runner.ExperimentOptions(variants=["proposed", "nope"]).chosen()
    assert {v.tracker for v in PAPER_VARIANTS.values()} == {"geometry", "klt"}


def test_latest_clip_frames_keeps_each_frame_once_from_its_latest_clip_position():
    # Two clips of 4 frames with stride 2 on one recording: frames 2 and 3 appear twice.
    times = np.array([0, 1, 2, 3, 2, 3, 4, 5])
    keep = latest_clip_frames(np.array(["r"] * 8), times, np.array([0, 1, 2, 3, 0, 1, 2, 3]))
    np.testing.assert_array_equal(times[keep], [0, 1, 2, 3, 4, 5])
    # Frames 2 and 3 come from the first clip (positions 2, 3 > 0, 1).
    np.testing.assert_array_equal(keep, [0, 1, 2, 3, 6, 7])


def _fake_predictions(noise: float, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    t = np.arange(120)
    true = np.stack([np.sin(t / 9), np.cos(t / 13), 0.3 * t / 120], axis=1)
    true = np.concatenate([true, true * 1.5])
    return dict(recording=np.array(["c"] * 120 + ["d"] * 120), orientation_deg=np.array([90.0] * 120 + [180.0] * 120),
                frame_time_ns=np.concatenate([t, t]).astype(np.int64) * 33_333_333,
                pred=true + noise * rng.standard_normal(true.shape), true=true)


def _fake_runs(out, noise_by_variant: dict[str, float], seeds: int = 2):
    for variant, noise in noise_by_variant.items():
        for seed in range(seeds):
            run = out / "runs" / variant / f"seed{seed}"
            run.mkdir(parents=True)
            predictions = _fake_predictions(noise, seed)
            np.savez_compressed(run / "predictions.npz", **predictions)
            (run / "metrics.json").write_text(json.dumps({"force_fps": 5000.0}))


def test_reports_from_run_folders(tmp_path):
    manifest = write_manifest(tmp_path)
    out = tmp_path / "results"
    _fake_runs(out, {"proposed": 0.05, "camera_frame": 0.2, "klt": 0.08, "rgb": 0.3})
    paths = report.write_reports(out, manifest)
    table1 = paths["table1.md"].read_text()
    table2 = paths["table2.md"].read_text()
    assert "Proposed" in table1 and "RGB only" in table1 and "Camera frame" not in table1
    assert "Camera frame" in table2 and "KLT" in table2 and "RGB" not in table2
    runs = report.load_runs(out)
    expected = tables.aggregate_seeds(runs["proposed"])["value"]["rmse"]
    assert f"{expected:.3f}" in table1
    for key in ("table1.csv", "table1.tex", "table2.csv", "table2.tex", "fig7"):
        assert paths[key].is_file() and paths[key].stat().st_size > 0
    claims = json.loads(paths["claims"].read_text())
    assert claims["object_frame_halves_rmse"]["holds"] is True  # 0.05 vs 0.2 noise
    assert claims["geometry_beats_klt"]["holds"] is True and claims["beats_rgb"]["holds"] is True
    assert "beats_position_only" not in claims
    text = report.summary_text(paths)
    assert "Table I" in text and "fig7" in text and "object frame lowers the average RMSE" in text


def _rmse_by_hand(predictions: dict) -> float:
    """Table I's average RMSE of one run: per component sqrt(mean squared error) over every test frame,
    averaged over Fx, Fy, Fz."""
    return float(np.sqrt(((predictions["pred"] - predictions["true"]) ** 2).mean(axis=0)).mean())


def test_experiment_reports_only_from_the_command_line(tmp_path, capsys):
    from vfdata.cli import main

    manifest = write_manifest(tmp_path)
    out = tmp_path / "results"
    _fake_runs(out, {"visionforce": 0.1, "proposed": 0.3})
    assert main(["experiment", str(manifest), "--out", str(out), "--reports-only"]) == 0
    printed = capsys.readouterr().out
    assert "Table I" in printed and str(out / "table1_force.md") in printed
    rows = [line.split("|") for line in (out / "table1_force.md").read_text().splitlines() if "RMSE (N)" in line]
    averages = {row[1].strip(): float(row[-2].split("±")[0]) for row in rows}
    for variant, noise, label in (("visionforce", 0.1, "VisionForce"), ("proposed", 0.3, "Proposed")):
        expected = np.mean([_rmse_by_hand(_fake_predictions(noise, seed)) for seed in range(2)])
        (got,) = [value for name, value in averages.items() if name.startswith(label)]
        assert got == pytest.approx(expected, abs=5e-4), variant


def test_claims_flag_a_failed_claim():
    agg = {name: {"value": {"rmse": rmse}} for name, rmse in
           (("proposed", 0.8), ("camera_frame", 1.0), ("velocity_only", 0.7), ("canonical_side", 0.45),
            ("klt", 0.6), ("geometry_plus", 0.5))}
    result = report.claims(agg)
    assert result["object_frame_halves_rmse"]["holds"] is False
    assert result["object_frame_halves_rmse"]["reduction"] == pytest.approx(0.2)
    assert result["beats_velocity_only"]["holds"] is False
    assert result["object_frame_halves_rmse_canonical_side"]["holds"] is True
    assert result["object_frame_halves_rmse_canonical_side"]["reduction"] == pytest.approx(0.55)
    assert result["geometry_beats_klt"]["holds"] is False
    assert result["geometry_plus_beats_klt"]["holds"] is True


@pytest.mark.slow
def test_experiment_end_to_end_on_a_tiny_simulated_dataset(tmp_path):
    """Synthesis -> conversion -> processing (geometry and KLT) -> training -> test -> reports, then a
    second call that repeats nothing."""
    from vfdata.sim import synthesize

    manifest = synthesize("mini", tmp_path / "data", seed=0, workers=2, progress=False, frames=40)
    options = runner.ExperimentOptions(seeds=1, epochs=1, variants=["proposed", "klt"], workers=2,
                                           progress=False)
    result = runner.run_experiment(manifest, tmp_path / "results", options)
    assert (tmp_path / "data" / "mini_002.klt.mcap").is_file()
    for variant in ("proposed", "klt"):
        run = tmp_path / "results" / "runs" / variant / "seed0"
        metrics = json.loads((run / "metrics.json").read_text())
        predictions = dict(np.load(run / "predictions.npz"))
        tables.check_predictions(predictions)
        assert set(predictions["recording"]) == {"mini_002"} and metrics["test_frames"] == len(predictions["true"])
        assert len(np.unique(predictions["frame_time_ns"])) == len(predictions["frame_time_ns"])
        assert metrics["pooled"]["rmse"] == pytest.approx(_rmse_by_hand(predictions), rel=1e-6)
        with Recording.open(tmp_path / "data" / "mini_002.mcap") as rec:  # the sensor's force at those frames
            np.testing.assert_allclose(predictions["true"], rec.force_at(predictions["frame_time_ns"])[:, :3],
                                       rtol=1e-5, atol=1e-5)
    for key in ("table1.md", "table2.md", "table3.md", "timing.md", "fig5", "fig6", "fig7", "training",
                "first_frames"):
        assert result.reports[key].is_file(), key
    assert "KLT" in result.reports["table3.md"].read_text()
    stamp = (tmp_path / "results" / "runs" / "proposed" / "seed0" / "metrics.json").stat().st_mtime_ns
    again = runner.run_experiment(manifest, tmp_path / "results", options)
    assert (tmp_path / "results" / "runs" / "proposed" / "seed0" / "metrics.json").stat().st_mtime_ns == stamp
    assert again.seconds["train_test"] < 5.0


def test_transfer_table_compares_each_test_orientation_with_validation(tmp_path):
    """A run's metrics.json with the validation split's metrics ("val", as write_run writes it) gives a
    transfer table: the validation RMSE, each orientation's, and the worst orientation's ratio."""
    from vfmodels.experiment.runs import write_run

    manifest = write_manifest(tmp_path)
    out = tmp_path / "results"
    run = out / "runs" / "visionforce" / "seed0"
    run.mkdir(parents=True)
    test = _fake_predictions(0.2, 0)
    validation = {**_fake_predictions(0.1, 1), "orientation_deg": np.zeros(len(test["true"]))}
    summary = write_run(run, test, {"variant": "visionforce"}, validation)
    assert summary["val"]["rmse"] < summary["pooled"]["rmse"]
    paths = report.write_reports(out, manifest)
    text = paths["transfer.md"].read_text()
    per = {float(k): g["rmse"] for k, g in summary["groups"].items()}
    worst = max(per.values()) / summary["val"]["rmse"]
    assert f"{summary['val']['rmse']:.3f}" in text and f"{worst:.2f}" in text
    assert all(f"{a:g}°" in text for a in per)


def test_the_report_gives_the_bands_coverage_and_width_per_view(tmp_path, capsys):
    """A run whose frames carry a band (as a model with a calibration writes them): metrics.json and band.md
    give its coverage and mean half-width per component, pooled and per test view, and the command prints
    them; validation.npz keeps the frames it was calibrated on."""
    from vfdata.cli import main
    from vfmodels.experiment.runs import write_run

    manifest = write_manifest(tmp_path)
    out = tmp_path / "results"
    run = out / "runs" / "visionforce" / "seed0"
    run.mkdir(parents=True)
    test = _fake_predictions(0.2, 0)
    # a band of +-0.33 N: 90% of N(0, 0.2) errors at 90°; the 180° view's error is three times as large
    test["pred"][120:] = test["true"][120:] + 3 * (test["pred"][120:] - test["true"][120:])
    test["band"], test["spread"] = np.full_like(test["true"], 0.33), np.zeros_like(test["true"])
    validation = {**_fake_predictions(0.2, 1), "orientation_deg": np.zeros(240)}
    summary = write_run(run, test, {"variant": "visionforce"}, validation)
    assert set(dict(np.load(run / "validation.npz"))) >= {"pred", "true"}
    cover = {float(k): g["coverage"] for k, g in summary["band"]["groups"].items()}
    assert cover[90.0] > 0.8 > 0.5 > cover[180.0] and summary["band"]["pooled"]["half_width_fz"] == pytest.approx(0.33)
    assert main(["experiment", str(manifest), "--out", str(out), "--reports-only"]) == 0
    printed = capsys.readouterr().out
    rows = {line.split("|")[2].strip(): line.split("|") for line in (out / "band.md").read_text().splitlines()
            if line.startswith("| VisionForce")}
    assert set(rows) == {"pooled", "90°", "180°"} and "How sure" in printed
    coverage = [float(v.strip(" %")) / 100 for v in rows["180°"][4].split("/")]
    assert np.mean(coverage) == pytest.approx(cover[180.0], abs=0.01)
    assert [float(v) for v in rows["90°"][5].split("/")] == [0.33, 0.33, 0.33]


@pytest.mark.slow
def test_quickstart_from_the_command_line(tmp_path, capsys):
    """`vfdata quickstart` (one epoch of `visionforce`): Table I printed with the run's RMSE, recomputed here
    from its test predictions; a second call makes nothing new."""
    from vfdata.cli import main

    args = ["quickstart", str(tmp_path / "qs"), "--epochs", "1", "--variants", "visionforce", "--workers", "2"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    run = tmp_path / "qs" / "results" / "runs" / "visionforce" / "seed0"
    rmse = _rmse_by_hand(dict(np.load(run / "predictions.npz")))
    assert "Table I" in printed and f"{rmse:.3f} ± n/a" in printed
    stamp = (run / "metrics.json").stat().st_mtime_ns
    assert main(args) == 0 and (run / "metrics.json").stat().st_mtime_ns == stamp
    assert f"{rmse:.3f} ± n/a" in capsys.readouterr().out
