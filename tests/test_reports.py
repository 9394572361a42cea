"""Report tables and plots from synthetic arrays with known metrics."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import cv2
import numpy as np
import pytest

from vfmodels.reports import figures, tables


def predictions(noise: float, seed: int = 0, orientations=(90.0, 180.0), frames: int = 200) -> dict:
    rng = np.random.default_rng(seed)
    parts = []
    for k, orientation in enumerate(orientations):
        t = np.arange(frames)
        true = np.stack([np.sin(t / 10.0), 2 * np.cos(t / 15.0), 0.5 * np.sin(t / 7.0) + 1], axis=1)
        pred = true + noise * (k + 1) * rng.standard_normal(true.shape)
        parts.append(dict(recording=np.full(frames, f"rec_{k}"), orientation_deg=np.full(frames, orientation),
                          frame_time_ns=(t * 33_333_333).astype(np.int64), pred=pred, true=true))
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


def test_perfect_predictions_give_zero_error_and_unit_r2():
    result = tables.run_metrics(predictions(0.0))
    assert result["pooled"]["rmse"] == pytest.approx(0.0, abs=1e-12)
    assert result["pooled"]["r2"] == pytest.approx(1.0)
    assert set(result["groups"]) == {90.0, 180.0}


def test_run_metrics_matches_hand_computation_and_orientation_spread():
    p = predictions(0.1)
    result = tables.run_metrics(p)
    err = p["pred"] - p["true"]
    assert result["pooled"]["rmse_fx"] == pytest.approx(np.sqrt(np.mean(err[:, 0] ** 2)))
    per = [np.sqrt(np.mean(err[p["orientation_deg"] == o] ** 2, axis=0)).mean() for o in (90.0, 180.0)]
    assert result["std"]["rmse"] == pytest.approx(np.std(per))
    # The second orientation has twice the noise: its RMSE is about twice the first's.
    assert per[1] / per[0] == pytest.approx(2.0, rel=0.15)


def test_run_metrics_skips_frames_without_force():
    p = predictions(0.1)
    p["true"][:10] = np.nan
    assert np.isfinite(tables.run_metrics(p)["pooled"]["rmse"])


def test_check_predictions_names_the_problem():
    p = predictions(0.1)
    del p["frame_time_ns"]
    with pytest.raises(ValueError, match="frame_time_ns"):
        tables.check_predictions(p)
    p = predictions(0.1)
    p["pred"] = p["pred"][:-1]
    with pytest.raises(ValueError, match="'pred' has"):
        tables.check_predictions(p)


def test_aggregate_seeds_means_and_spreads():
    runs = [tables.run_metrics(predictions(0.1, seed=s)) for s in range(3)]
    agg = tables.aggregate_seeds(runs)
    values = [r["pooled"]["rmse"] for r in runs]
    assert agg["value"]["rmse"] == pytest.approx(np.mean(values))
    assert agg["seed_std"]["rmse"] == pytest.approx(np.std(values))
    assert agg["orientation_std"]["rmse"] == pytest.approx(np.mean([r["std"]["rmse"] for r in runs]))
    assert agg["seeds"] == 3
    with pytest.raises(ValueError):
        tables.aggregate_seeds([])


def _table():
    return {
        "proposed": tables.aggregate_seeds([tables.run_metrics(predictions(0.05, seed=s)) for s in range(2)]),
        "camera_frame": tables.aggregate_seeds([tables.run_metrics(predictions(0.3, seed=s)) for s in range(2)]),
    }


def test_markdown_table_has_every_model_metric_and_value():
    table = _table()
    text = tables.force_table_markdown(table, {"proposed": "Proposed", "camera_frame": "Camera frame"}, "Table I")
    assert "**Table I**" in text
    assert text.count("| Proposed | RMSE (N) |") == 1 and "| Camera frame | RMSE (N) |" in text
    assert f"{table['proposed']['value']['rmse']:.3f} ± {table['proposed']['orientation_std']['rmse']:.3f}" in text
    assert len([line for line in text.splitlines() if line.startswith("|")]) == 2 + 2 * 3


def test_csv_round_trips_the_values():
    table = _table()
    rows = list(csv.DictReader(io.StringIO(tables.force_table_csv(table))))
    assert len(rows) == 2 * 3 * 4
    row = next(r for r in rows if r["model"] == "camera_frame" and r["metric"] == "r2" and r["component"] == "Fy")
    assert float(row["value"]) == pytest.approx(table["camera_frame"]["value"]["r2_fy"])
    assert float(row["seed_std"]) == pytest.approx(table["camera_frame"]["seed_std"]["r2_fy"])


def test_latex_marks_the_best_value_bold():
    table = _table()
    text = tables.force_table_latex(table, {"camera_frame": "Camera_frame & co"}, caption="RMSE 50% lower")
    best = f"\\textbf{{{table['proposed']['value']['rmse']:.3f}}}"
    assert best in text
    assert r"Camera\_frame \& co" in text and r"50\%" in text
    assert text.count(r"\\") >= 1 + 2 * 3
    assert "\\begin{tabular}" in text and "\\end{table}" in text


def test_write_force_table_writes_three_files(tmp_path):
    paths = tables.write_force_table(tmp_path / "tables", "table1", _table(), title="Table I")
    assert sorted(p.suffix for p in paths.values()) == [".csv", ".md", ".tex"]
    assert all(p.stat().st_size > 100 for p in paths.values())


def test_relative_change():
    assert tables.relative_change(0.49, 1.0) == pytest.approx(-0.51)


def test_end_to_end_fps_is_harmonic():
    assert tables.end_to_end_fps({"depth": 20.0, "tracking": 20.0}) == pytest.approx(10.0)
    assert tables.end_to_end_fps({"depth": 20.0, "x": 1.0}, ["depth"]) == pytest.approx(20.0)


def test_combine_stage_fps_weights_by_frames():
    # 100 frames at 10 fps (10 s) + 300 frames at 100 fps (3 s) = 400 frames in 13 s.
    combined = tables.combine_stage_fps([{"depth": 10.0}, {"depth": 100.0}], [100, 300])
    assert combined["depth"] == pytest.approx(400 / 13)


def test_timing_table_lists_stages_and_end_to_end():
    text = tables.timing_table_markdown({"depth": 20.0, "mask": 100.0, "tracking": 50.0, "force": 1000.0,
                                          "write": 5.0})
    assert "| Depth | 20.0 | 50.00 |" in text
    e2e = 1 / (1 / 20 + 1 / 100 + 1 / 50 + 1 / 1000)
    assert f"**{e2e:.1f}**" in text
    assert "Write" not in text


def test_tracking_table_shows_error_columns_only_with_ground_truth():
    rows = {"geometry": {"coverage_mean": 0.72, "coverage_std": 0.05, "nni_mean": 1.02, "nni_std": 0.01, "peaks": 9},
            "klt": {"coverage_mean": 0.41, "coverage_std": 0.1, "nni_mean": 0.8, "nni_std": 0.1, "peaks": 9}}
    text = tables.tracking_table_markdown(rows, {"geometry": "Geometry"})
    assert "| Geometry | 9 | 72.00 ± 5.00 | 1.020 ± 0.010 |" in text
    assert "median" not in text
    rows["geometry"]["normal_median_mm"] = 0.2
    text = tables.tracking_table_markdown(rows)
    assert "Normal median (mm)" in text and "0.200" in text
    assert "| klt | 9 | 41.00 ± 10.00 | 0.800 ± 0.100 | – |" in text
    assert "normal_median_mm" in tables.tracking_table_csv(rows).splitlines()[0]


def _is_png(path) -> bool:
    image = cv2.imread(str(path))
    return image is not None and image.shape[0] > 100 and image.shape[1] > 100


def test_force_curve_plot(tmp_path):
    path = figures.plot_force_curves(predictions(0.1), tmp_path / "fig7.png", title="test")
    assert _is_png(path)


def test_force_kde_integrates_to_one_and_peaks_at_the_mode():
    rng = np.random.default_rng(0)
    samples = rng.normal(2.0, 0.5, 5000)
    grid = np.linspace(-2, 6, 801)
    density = figures.force_kde(samples, grid)
    assert np.trapezoid(density, grid) == pytest.approx(1.0, abs=0.01)
    assert grid[np.argmax(density)] == pytest.approx(2.0, abs=0.15)
    spike = figures.force_kde(np.full(10, 1.0), grid)
    assert np.trapezoid(spike, grid) == pytest.approx(1.0, abs=0.01)


def test_force_distribution_plot(tmp_path):
    rng = np.random.default_rng(1)
    path = figures.plot_force_distributions(rng.normal(size=(500, 3)), rng.normal(1, 2, size=(300, 3)),
                                            tmp_path / "fig5.png")
    assert _is_png(path)


def test_tracked_points_plot(tmp_path):
    image = np.full((120, 160, 3), 80, np.uint8)
    mask = np.zeros((120, 160), bool)
    mask[30:90, 40:120] = True
    uv = np.stack(np.meshgrid(np.linspace(45, 115, 8), np.linspace(35, 85, 8)), -1).reshape(-1, 2)
    lost = uv.copy()
    lost[::3] = np.nan
    path = figures.plot_tracked_points(image, {"geometry": (uv, np.ones(64, bool)),
                                               "klt": (lost, np.arange(64) % 2 == 0)}, tmp_path / "fig6.png", mask)
    assert _is_png(path)


def _write_log(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True)
    columns = ["epoch", "step", *tables.EPOCH_COLUMNS]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, columns)
        writer.writeheader()
        writer.writerows(rows)


def test_epoch_curves_join_resumed_versions(tmp_path):
    """A run resumed in epoch 2 logs epoch 2 again in its next version (the later value counts); the
    versions are taken by number (version_10 after version_2); step rows without epoch values and
    columns that were not logged give NaN."""
    run = tmp_path / "runs" / "proposed" / "seed0"
    _write_log(run / "csv" / "version_0" / "metrics.csv", [
        {"epoch": 0, "step": 9},  # a step row: no epoch values
        {"epoch": 0, "step": 10, "train/loss_epoch": 0.9, "time/epoch_s": 60.0},
        {"epoch": 0, "step": 10, "val/loss": 0.8},
        {"epoch": 1, "step": 20, "train/loss_epoch": 0.7, "val/loss": 0.6, "time/epoch_s": 50.0},
        {"epoch": 2, "step": 30, "train/loss_epoch": 0.65},  # interrupted before validation
    ])
    _write_log(run / "csv" / "version_2" / "metrics.csv", [
        {"epoch": 2, "step": 30, "train/loss_epoch": 0.5, "val/loss": 0.4, "time/epoch_s": 40.0},
    ])
    _write_log(run / "csv" / "version_10" / "metrics.csv", [
        {"epoch": 3, "step": 40, "train/loss_epoch": 0.45, "val/loss": 0.5, "time/epoch_s": 41.0},
    ])
    curves = tables.read_epoch_curves(run)
    assert curves["epoch"].tolist() == [0, 1, 2, 3]
    assert curves["train/loss_epoch"].tolist() == [0.9, 0.7, 0.5, 0.45]
    assert curves["val/loss"].tolist() == [0.8, 0.6, 0.4, 0.5]
    assert curves["time/epoch_s"].tolist() == [60.0, 50.0, 40.0, 41.0]
    assert np.isnan(curves["time/epoch_cpu_s"]).all()
    path = figures.plot_training_curves({"proposed seed0": curves}, tmp_path / "curves.png", title="test")
    assert _is_png(path)
    assert tables.read_epoch_curves(tmp_path / "empty")["epoch"].tolist() == []
    assert tables.training_summary(curves) == {"epochs": 4, "best_epoch": 2}
    no_validation = {"epoch": np.array([0, 1]), "val/loss": np.array([np.nan, np.nan])}
    assert tables.training_summary(no_validation) == {"epochs": 2, "best_epoch": None}


def test_first_frames_side_by_side(tmp_path):
    images = {f"rec_{k} (90 deg)": np.full((48, 64, 3), 40 * k, np.uint8) for k in range(3)}
    path = figures.plot_first_frames(images, tmp_path / "first.png", title="test")
    assert _is_png(path)
    height, width = cv2.imread(str(path)).shape[:2]
    assert 1.0 < width / height < 1.6  # two to a row, two rows (one row of three would be ~3.5)


def test_tables_say_how_long_each_model_trained():
    """Runs of unequal length in one table (a 20-epoch ablation beside 60-epoch runs) are named with
    their epochs and best epoch per seed; models without logs are left out of that line."""
    runs = [tables.run_metrics(predictions(0.05, seed=s)) for s in range(3)]
    runs[0]["training"] = {"epochs": 60, "best_epoch": 4}
    runs[1]["training"] = {"epochs": 20, "best_epoch": None}  # seed 2: no logs
    table = {"proposed": tables.aggregate_seeds(runs),
             "camera_frame": tables.aggregate_seeds([tables.run_metrics(predictions(0.3))])}
    text = tables.force_table_markdown(table, {"proposed": "Proposed"})
    assert text.splitlines()[-1].endswith("one per seed): Proposed 60/20/? (4/–/?).")
    rows = list(csv.DictReader(io.StringIO(tables.force_table_csv(table))))
    assert {r["epochs_best"] for r in rows if r["model"] == "proposed"} == {"60/20/? (4/–/?)"}
    assert {r["epochs_best"] for r in rows if r["model"] == "camera_frame"} == {""}
