"""Tables and plots of an experiment (docs/experiments.md): pure functions from arrays and dicts to
text and image files. Nothing here reads MCAP or runs a model; `vfdata.experiment` gathers the inputs.

Force tables (the paper's Tables I and II). For every model variant and seed, the test frames give
RMSE (N), NRMSE and R^2 per component (Fx, Fy, Fz) and their average, pooled over all test frames,
and the same per test orientation. A table cell is the pooled value averaged over seeds, +- the
standard deviation across test orientations (also averaged over seeds); the CSV keeps the spread
across seeds as well.

Tracking table (Table III): coverage and NNI at force peaks per tracker; with simulator ground truth
also the 3D tracking error (median / 95th percentile, mm) split along and across the surface normal.

Timing table: frames/s of each stage (depth, mask, tracking, force prediction) and end to end, where
the end-to-end rate is the harmonic combination of the sequential stages, 1 / sum(1 / fps).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from vfmodels.metrics import COMPONENTS, grouped_force_metrics

METRICS = (("rmse", "RMSE (N)"), ("nrmse", "NRMSE"), ("r2", "R²"))
COLUMNS = (("fx", "Fx"), ("fy", "Fy"), ("fz", "Fz"), ("", "Avg"))
PREDICTION_KEYS = ("recording", "orientation_deg", "frame_time_ns", "pred", "true")


# ---- force metrics over seeds --------------------------------------------------------------------


def check_predictions(predictions: Mapping[str, np.ndarray], where: str = "predictions") -> None:
    """Raise ValueError unless `predictions` has the keys of predictions.npz with matching lengths:
    recording (M,) str, orientation_deg (M,), frame_time_ns (M,) int64, pred (M, 3) N, true (M, 3) N."""
    missing = [k for k in PREDICTION_KEYS if k not in predictions]
    if missing:
        raise ValueError(f"{where}: missing {', '.join(missing)}")
    m = len(predictions["true"])
    for key in PREDICTION_KEYS:
        if len(predictions[key]) != m:
            raise ValueError(f"{where}: '{key}' has {len(predictions[key])} rows, 'true' has {m}")
    for key in ("pred", "true"):
        if np.asarray(predictions[key]).shape != (m, 3):
            raise ValueError(f"{where}: '{key}' must be (M, 3), got {np.asarray(predictions[key]).shape}")


def run_metrics(predictions: Mapping[str, np.ndarray]) -> dict:
    """Metrics of one run from its test frames: {"pooled", "mean", "std", "groups"} as
    `vfmodels.metrics.grouped_force_metrics`, grouped by orientation (deg)."""
    check_predictions(predictions)
    known = np.isfinite(predictions["true"]).all(axis=1) & np.isfinite(predictions["pred"]).all(axis=1)
    orientation = np.asarray(predictions["orientation_deg"], dtype=np.float64)[known]
    return grouped_force_metrics(np.asarray(predictions["pred"])[known], np.asarray(predictions["true"])[known],
                                 orientation)


def aggregate_seeds(runs: Sequence[Mapping]) -> dict:
    """Per metric key (e.g. "rmse_fx", "r2"): the pooled value's mean and std over seeds, and the
    across-orientation std averaged over seeds. Input: a list of `run_metrics` results (one per seed).
    Returns {"value": {...}, "orientation_std": {...}, "seed_std": {...}, "seeds": n}."""
    if not runs:
        raise ValueError("no runs to aggregate")
    keys = list(runs[0]["pooled"])
    pooled = np.array([[r["pooled"][k] for k in keys] for r in runs], dtype=np.float64)
    # A single test orientation has no spread across orientations: 0, as grouped_force_metrics gives.
    spread = np.array([[r.get("std", {}).get(k, 0.0) for k in keys] for r in runs], dtype=np.float64)
    return {
        "value": dict(zip(keys, pooled.mean(axis=0).tolist(), strict=True)),
        "orientation_std": dict(zip(keys, spread.mean(axis=0).tolist(), strict=True)),
        "seed_std": dict(zip(keys, pooled.std(axis=0).tolist(), strict=True)),
        "seeds": len(runs),
        # Runs of one results folder may differ in length (resumed, or re-run with another --epochs);
        # a table must say so, or a 20-epoch ablation reads as a 60-epoch one.
        "training": [r.get("training") for r in runs],  # None for a seed without logs
    }


def relative_change(value: float, reference: float) -> float:
    """(value - reference) / reference, e.g. -0.51 for a 51 % lower RMSE."""
    return (value - reference) / reference if reference else float("nan")


# ---- force tables --------------------------------------------------------------------------------


def _fmt(value: float, digits: int = 3) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def force_table_rows(table: Mapping[str, Mapping], labels: Mapping[str, str] | None = None) -> list[dict]:
    """Long-form rows (one per model, metric and component) from {variant: aggregate_seeds(...)}:
    model, label, metric, component, value, orientation_std, seed_std, seeds, epochs_best ("60 (4)":
    epochs trained and best validation epoch per seed, empty when unknown)."""
    labels = labels or {}
    rows = []
    for variant, agg in table.items():
        for metric, _ in METRICS:
            for comp, comp_label in COLUMNS:
                key = f"{metric}_{comp}" if comp else metric
                rows.append({
                    "model": variant, "label": labels.get(variant, variant), "metric": metric,
                    "component": comp_label, "value": agg["value"][key],
                    "orientation_std": agg["orientation_std"][key], "seed_std": agg["seed_std"][key],
                    "seeds": agg["seeds"], "epochs_best": _epochs_text(agg) if _has_training(agg) else "",
                })
    return rows


def force_table_markdown(table: Mapping[str, Mapping], labels: Mapping[str, str] | None = None,
                         title: str | None = None) -> str:
    """A Markdown table like the paper's: per model three rows (RMSE, NRMSE, R²) and columns Fx,
    Fy, Fz, Avg; cells "pooled ± std across test orientations" (means over seeds)."""
    labels = labels or {}
    lines = [f"**{title}**", ""] if title else []
    lines += ["| Model | Metric | Fx | Fy | Fz | Avg |", "| --- | --- | ---: | ---: | ---: | ---: |"]
    for variant, agg in table.items():
        for i, (metric, metric_label) in enumerate(METRICS):
            cells = []
            for comp, _ in COLUMNS:
                key = f"{metric}_{comp}" if comp else metric
                cells.append(f"{_fmt(agg['value'][key])} ± {_fmt(agg['orientation_std'][key])}")
            name = labels.get(variant, variant) if i == 0 else ""
            lines.append(f"| {name} | {metric_label} | " + " | ".join(cells) + " |")
    seeds = sorted({agg["seeds"] for agg in table.values()})
    lines += ["", f"Pooled over all test frames ± std across test orientations; mean over "
                  f"{'/'.join(map(str, seeds))} seed(s)."]
    trained = [f"{labels.get(variant, variant)} {_epochs_text(agg)}" for variant, agg in table.items()
               if _has_training(agg)]
    if trained:
        lines.append(f"Epochs trained (best validation epoch, counted from 0 as in the checkpoint names; "
                     f"one per seed): {'; '.join(trained)}.")
    return "\n".join(lines) + "\n"


def _has_training(agg: Mapping) -> bool:
    return any(t is not None for t in agg.get("training", []))


def _epochs_text(agg: Mapping) -> str:
    """"60 (4)", or "60/60 (4/7)" for two seeds; "?" for a seed without logs, "–" without validation."""
    runs = [t or {"epochs": "?", "best_epoch": "?"} for t in agg.get("training", [])]
    return (f"{'/'.join(str(t['epochs']) for t in runs)} "
            f"({'/'.join('–' if t['best_epoch'] is None else str(t['best_epoch']) for t in runs)})")


def force_table_csv(table: Mapping[str, Mapping], labels: Mapping[str, str] | None = None) -> str:
    out = io.StringIO()
    rows = force_table_rows(table, labels)
    writer = csv.DictWriter(out, fieldnames=list(rows[0]) if rows else ["model"], lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


def _latex_escape(text: str) -> str:
    for a, b in (("\\", r"\textbackslash{}"), ("&", r"\&"), ("%", r"\%"), ("_", r"\_"), ("#", r"\#"),
                 ("±", r"$\pm$"), ("²", r"$^2$")):
        text = text.replace(a, b)
    return text


def force_table_latex(table: Mapping[str, Mapping], labels: Mapping[str, str] | None = None,
                      caption: str = "", label: str = "tab:force") -> str:
    """A booktabs LaTeX table with the same content as the Markdown one; the best (lowest RMSE and
    NRMSE, highest R²) value of each column is bold."""
    labels = labels or {}
    best: dict[str, float] = {}
    for metric, _ in METRICS:
        for comp, _ in COLUMNS:
            key = f"{metric}_{comp}" if comp else metric
            values = [agg["value"][key] for agg in table.values() if math.isfinite(agg["value"][key])]
            if values:
                best[key] = max(values) if metric == "r2" else min(values)
    lines = [r"\begin{table}[t]", r"\centering", r"\caption{" + _latex_escape(caption) + "}",
             r"\label{" + label + "}", r"\begin{tabular}{llcccc}", r"\toprule",
             r"Model & Metric & $F_x$ & $F_y$ & $F_z$ & Avg \\", r"\midrule"]
    for n, (variant, agg) in enumerate(table.items()):
        for i, (metric, metric_label) in enumerate(METRICS):
            cells = []
            for comp, _ in COLUMNS:
                key = f"{metric}_{comp}" if comp else metric
                value = _fmt(agg["value"][key])
                if key in best and agg["value"][key] == best[key] and len(table) > 1:
                    value = r"\textbf{" + value + "}"
                cells.append(f"{value} $\\pm$ {_fmt(agg['orientation_std'][key])}")
            name = _latex_escape(labels.get(variant, variant)) if i == 0 else ""
            lines.append(f"{name} & {_latex_escape(metric_label)} & " + " & ".join(cells) + r" \\")
        if n < len(table) - 1:
            lines.append(r"\midrule")
    lines += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(lines) + "\n"


def write_force_table(folder: str | Path, stem: str, table: Mapping[str, Mapping],
                      labels: Mapping[str, str] | None = None, title: str = "") -> dict[str, Path]:
    """Write `<stem>.md`, `<stem>.csv` and `<stem>.tex` into `folder`; returns the paths by suffix."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    texts = {
        "md": force_table_markdown(table, labels, title),
        "csv": force_table_csv(table, labels),
        "tex": force_table_latex(table, labels, caption=title, label=f"tab:{stem}"),
    }
    paths = {}
    for suffix, text in texts.items():
        paths[suffix] = folder / f"{stem}.{suffix}"
        paths[suffix].write_text(text)
    return paths


# ---- tracking and timing tables ------------------------------------------------------------------

TRACKING_COLUMNS = (
    ("coverage_mean", "Coverage (%)", 100.0),
    ("nni_mean", "NNI", 1.0),
    ("full_median_mm", "3D err. median (mm)", 1.0),
    ("full_p95_mm", "3D err. p95 (mm)", 1.0),
    ("normal_median_mm", "Normal median (mm)", 1.0),
    ("normal_p95_mm", "Normal p95 (mm)", 1.0),
    ("tangential_median_mm", "Tangential median (mm)", 1.0),
    ("tangential_p95_mm", "Tangential p95 (mm)", 1.0),
)


def tracking_table_markdown(rows: Mapping[str, Mapping[str, float]], labels: Mapping[str, str] | None = None) -> str:
    """Table III: {tracker: {"coverage_mean", "coverage_std", "nni_mean", "nni_std", "peaks", and
    optionally the tracking-error keys of vfdata.metrics.TrackingError}} -> Markdown. Coverage and
    NNI are mean ± std over the force peaks of the test recordings; error columns appear only when
    some tracker has them (simulated data)."""
    labels = labels or {}
    columns = [c for c in TRACKING_COLUMNS if any(c[0] in r for r in rows.values())]
    lines = ["| Tracker | Peaks | " + " | ".join(c[1] for c in columns) + " |",
             "| --- | ---: | " + " | ".join("---:" for _ in columns) + " |"]
    for tracker, row in rows.items():
        cells = []
        for key, _, scale in columns:
            value = row.get(key, float("nan")) * scale
            std_key = key.replace("_mean", "_std")
            digits = 2 if scale > 1 else 3
            if key.endswith("_mean") and std_key in row:
                cells.append(f"{_fmt(value, digits)} ± {_fmt(row[std_key] * scale, digits)}")
            else:
                cells.append(_fmt(value, 3))
        lines.append(f"| {labels.get(tracker, tracker)} | {row.get('peaks', 0)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def tracking_table_csv(rows: Mapping[str, Mapping[str, float]]) -> str:
    keys = sorted({k for r in rows.values() for k in r})
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["tracker", *keys])
    for tracker, row in rows.items():
        writer.writerow([tracker, *[row.get(k, "") for k in keys]])
    return out.getvalue()


TIMING_STAGES = (("depth", "Depth"), ("mask", "Mask"), ("tracking", "Tracking"),
                 ("force", "Force prediction"))


def end_to_end_fps(stage_fps: Mapping[str, float], stages: Sequence[str] | None = None) -> float:
    """Frames/s of stages run one after another: 1 / sum(1 / fps). Missing stages are left out."""
    stages = stages if stages is not None else list(stage_fps)
    seconds = sum(1.0 / stage_fps[s] for s in stages if s in stage_fps and stage_fps[s] > 0)
    return 1.0 / seconds if seconds > 0 else float("inf")


def combine_stage_fps(per_recording: Sequence[Mapping[str, float]], frames: Sequence[int]) -> dict[str, float]:
    """Frames/s per stage over several recordings, weighted by their frames: total frames over
    total seconds (not the mean of rates, which would over-weight short fast recordings)."""
    totals: dict[str, float] = {}
    counts: dict[str, int] = {}
    for fps, n in zip(per_recording, frames, strict=True):
        for stage, rate in fps.items():
            if rate and rate > 0 and math.isfinite(rate):
                totals[stage] = totals.get(stage, 0.0) + n / rate
                counts[stage] = counts.get(stage, 0) + n
    return {stage: counts[stage] / totals[stage] for stage in totals if totals[stage] > 0}


def timing_table_markdown(stage_fps: Mapping[str, float], extra_stages: Sequence[str] = ("decode", "cloud")) -> str:
    """The per-stage timing table in frames/s and ms/frame. `stage_fps` has the stages of
    TIMING_STAGES (and optionally decode, cloud, object_frame, write); the end-to-end row combines
    every stage listed that ran per frame (all but object_frame and write, which are not part of a
    live pipeline)."""
    rows = [(key, label) for key, label in TIMING_STAGES if key in stage_fps]
    rows += [(key, key.replace("_", " ").capitalize()) for key in extra_stages if key in stage_fps]
    lines = ["| Stage | frames/s | ms/frame |", "| --- | ---: | ---: |"]
    for key, label in rows:
        fps = stage_fps[key]
        lines.append(f"| {label} | {_fmt(fps, 1)} | {_fmt(1000.0 / fps if fps > 0 else float('nan'), 2)} |")
    e2e = end_to_end_fps(stage_fps, [k for k, _ in rows])
    lines.append(f"| **End to end** | **{_fmt(e2e, 1)}** | **{_fmt(1000.0 / e2e, 2)}** |")
    return "\n".join(lines) + "\n"


# ---- training logs -------------------------------------------------------------------------------

EPOCH_COLUMNS = ("train/loss_epoch", "val/loss", "time/epoch_s", "time/epoch_cpu_s")


def epoch_curves(log_tables: Sequence[Sequence[Mapping[str, str]]]) -> dict[str, np.ndarray]:
    """Per-epoch values of a run from its Lightning CSV logs (`csv/version_N/metrics.csv`, rows as
    `csv.DictReader` gives them), oldest version first: a resumed run writes a new version that
    repeats the epoch it resumed in, and the later value wins. Returns {"epoch": (E,) int, and each
    of EPOCH_COLUMNS: (E,) float, NaN where not logged}; losses are normalised MSE, times seconds."""
    values: dict[int, dict[str, float]] = {}
    for rows in log_tables:
        for row in rows:
            if not row.get("epoch"):
                continue
            epoch = int(float(row["epoch"]))
            for column in EPOCH_COLUMNS:
                if row.get(column):
                    values.setdefault(epoch, {})[column] = float(row[column])
    epochs = sorted(values)
    curves = {"epoch": np.asarray(epochs, dtype=np.int64)}
    for column in EPOCH_COLUMNS:
        curves[column] = np.array([values[e].get(column, np.nan) for e in epochs], dtype=np.float64)
    return curves


def read_epoch_curves(run_dir: str | Path) -> dict[str, np.ndarray]:
    """`epoch_curves` of a run folder (every `csv/version_N/metrics.csv` under it, by N)."""
    def version(path: Path) -> int:
        return int(path.parent.name.rpartition("_")[2] or 0)

    tables = []
    for path in sorted(Path(run_dir).glob("csv/version_*/metrics.csv"), key=version):
        with open(path, newline="") as f:
            tables.append(list(csv.DictReader(f)))
    return epoch_curves(tables)


def training_summary(curves: Mapping[str, np.ndarray]) -> dict:
    """{"epochs": epochs logged, "best_epoch": the epoch (from 0) of the lowest validation loss, the
    checkpoint that testing uses, or None without validation} of an `epoch_curves` result."""
    val = np.asarray(curves.get("val/loss", []), dtype=np.float64)
    best = int(np.asarray(curves["epoch"])[np.nanargmin(val)]) if np.isfinite(val).any() else None
    return {"epochs": len(curves["epoch"]), "best_epoch": best}


# ---- plots ---------------------------------------------------------------------------------------


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_force_curves(predictions: Mapping[str, np.ndarray], path: str | Path, fps: float = 30.0,
                      title: str = "", max_recordings: int | None = None) -> Path:
    """Fig. 7: measured (solid) and predicted (dashed) Fx, Fy, Fz against time, one column per test
    orientation (its first recording, or `max_recordings` of them one after another)."""
    plt = _pyplot()
    check_predictions(predictions)
    orientation = np.asarray(predictions["orientation_deg"], dtype=np.float64)
    groups = np.unique(orientation)
    fig, axes = plt.subplots(3, len(groups), figsize=(5.0 * len(groups), 6.5), sharex="col", squeeze=False)
    colours = ("tab:red", "tab:green", "tab:blue")
    for col, group in enumerate(groups):
        sel = np.flatnonzero(orientation == group)
        recordings = list(dict.fromkeys(np.asarray(predictions["recording"])[sel].astype(str)))
        if max_recordings is not None:
            recordings = recordings[:max_recordings]
        offset_s = 0.0
        for rec in recordings:
            idx = sel[np.asarray(predictions["recording"])[sel].astype(str) == rec]
            idx = idx[np.argsort(np.asarray(predictions["frame_time_ns"])[idx])]
            t_ns = np.asarray(predictions["frame_time_ns"], dtype=np.int64)[idx]
            t = (t_ns - t_ns[0]) / 1e9 + offset_s
            for row, comp in enumerate(COMPONENTS):
                ax = axes[row, col]
                ax.plot(t, predictions["true"][idx, row], color=colours[row], lw=1.2,
                        label="measured" if rec == recordings[0] else None)
                ax.plot(t, predictions["pred"][idx, row], color="black", lw=1.0, ls="--",
                        label="predicted" if rec == recordings[0] else None)
                ax.set_ylabel(f"F{comp[1]} (N)")
            offset_s = t[-1] + 1.0 / fps if len(t) else offset_s
        axes[0, col].set_title(f"{group:g}° ({len(recordings)} recording{'s' * (len(recordings) > 1)})")
        axes[-1, col].set_xlabel("time (s)")
        axes[0, col].legend(loc="upper right", fontsize=8)
    for ax in axes.ravel():
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def save_figure(fig, path: str | Path) -> Path:
    """Lay out, write (PNG, 120 dpi, creating the folder) and close a matplotlib figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def force_kde(samples: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Gaussian kernel density (Scott's bandwidth) of 1-D `samples` on `grid`; a degenerate sample
    (fewer than two distinct values) gives a narrow spike of unit area at its value."""
    from scipy.stats import gaussian_kde

    samples = np.asarray(samples, dtype=np.float64)
    samples = samples[np.isfinite(samples)]
    if len(np.unique(samples)) < 2:
        density = np.zeros_like(grid, dtype=np.float64)
        if len(samples):
            step = grid[1] - grid[0] if len(grid) > 1 else 1.0
            density[np.argmin(np.abs(grid - samples[0]))] = 1.0 / step
        return density
    return gaussian_kde(samples)(grid)


def plot_force_distributions(train_n: np.ndarray, test_n: np.ndarray, path: str | Path,
                             labels: tuple[str, str] = ("train", "test"), title: str = "",
                             max_samples: int = 20000, seed: int = 0) -> Path:
    """Fig. 5: kernel density estimates of Fx, Fy, Fz (N) of the training and test frames."""
    plt = _pyplot()
    rng = np.random.default_rng(seed)
    sets = []
    for forces in (train_n, test_n):
        forces = np.asarray(forces, dtype=np.float64).reshape(-1, 3)
        forces = forces[np.isfinite(forces).all(axis=1)]
        if len(forces) > max_samples:  # a KDE on 20k points is already smooth; more only costs time
            forces = forces[rng.choice(len(forces), max_samples, replace=False)]
        sets.append(forces)
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for k, comp in enumerate(COMPONENTS):
        values = np.concatenate([s[:, k] for s in sets])
        lo, hi = (values.min(), values.max()) if len(values) else (-1.0, 1.0)
        pad = 0.1 * (hi - lo) + 1e-3
        grid = np.linspace(lo - pad, hi + pad, 400)
        for forces, label, colour in zip(sets, labels, ("tab:blue", "tab:orange"), strict=True):
            if len(forces):
                density = force_kde(forces[:, k], grid)
                axes[k].plot(grid, density, color=colour, label=f"{label} ({len(forces)} frames)")
                axes[k].fill_between(grid, density, color=colour, alpha=0.2)
        axes[k].set_xlabel(f"F{comp[1]} (N)")
        axes[k].grid(alpha=0.3)
    axes[0].set_ylabel("density")
    axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def plot_training_curves(curves: Mapping[str, Mapping[str, np.ndarray]], path: str | Path, title: str = "") -> Path:
    """Training and validation loss (normalised MSE) against the epoch, one colour per run
    ({label: `epoch_curves` result}); a dot marks each run's best validation epoch, the checkpoint
    that testing uses. The legend gives the epochs and the summed epoch wall time."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 4.2))
    palette = plt.get_cmap("tab10" if len(curves) <= 10 else "tab20")  # a full grid has 11 or more runs
    for k, (label, run) in enumerate(curves.items()):
        colour = palette(k % palette.N)
        epochs = np.asarray(run["epoch"])
        minutes = np.nansum(run["time/epoch_s"]) / 60.0
        ax.plot(epochs, run["train/loss_epoch"], color=colour, alpha=0.5, linestyle="--")
        val = np.asarray(run["val/loss"], dtype=np.float64)
        ax.plot(epochs, val, color=colour, label=f"{label}: {len(epochs)} epochs, {minutes:.0f} min")
        best = training_summary(run)["best_epoch"]
        if best is not None:
            ax.plot(best, val[epochs == best][0], "o", color=colour)
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss (normalised MSE)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3, which="both")
    ax.plot([], [], color="grey", linestyle="--", alpha=0.5, label="training (dashed)")
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    return save_figure(fig, path)


def plot_first_frames(images: Mapping[str, np.ndarray], path: str | Path, title: str = "") -> Path:
    """The first-frame pictures of several recordings ({title: BGR image}, e.g.
    `vfdata.recon.preview.first_frame_preview`) side by side, two to a row."""
    plt = _pyplot()
    cols = min(2, len(images))
    rows = -(-len(images) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6.4 * cols, 5.4 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (label, image) in zip(axes.ravel(), images.items(), strict=False):
        ax.imshow(np.ascontiguousarray(image[..., ::-1]))
        ax.set_title(label, fontsize=10)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def plot_tracked_points(image_bgr: np.ndarray, tracks: Mapping[str, tuple[np.ndarray, np.ndarray]],
                        path: str | Path, mask: np.ndarray | None = None, title: str = "") -> Path:
    """Fig. 6: tracked points of each tracker on the left image of one (peak) frame, side by side.
    tracks: {label: (points_uv (N, 2) px, visible (N,) bool)}; lost or invisible points are drawn
    hollow, visible ones filled. The tissue mask outline is drawn when given."""
    plt = _pyplot()
    rgb = np.asarray(image_bgr)[..., ::-1]
    fig, axes = plt.subplots(1, len(tracks), figsize=(5.2 * len(tracks), 4.4), squeeze=False)
    for ax, (label, (uv, visible)) in zip(axes[0], tracks.items(), strict=True):
        uv = np.asarray(uv, dtype=np.float64)
        visible = np.asarray(visible, dtype=bool) & np.isfinite(uv).all(axis=1)
        ax.imshow(rgb)
        if mask is not None and np.asarray(mask).any():
            ax.contour(np.asarray(mask).astype(float), levels=[0.5], colors="white", linewidths=0.8)
        ax.scatter(uv[visible, 0], uv[visible, 1], s=9, c="yellow", edgecolors="black", linewidths=0.3)
        hidden = ~visible & np.isfinite(uv).all(axis=1)
        ax.scatter(uv[hidden, 0], uv[hidden, 1], s=9, facecolors="none", edgecolors="cyan", linewidths=0.5)
        ax.set_title(f"{label}: {int(visible.sum())}/{len(uv)} visible")
        ax.set_xlim(0, rgb.shape[1])
        ax.set_ylim(rgb.shape[0], 0)
        ax.axis("off")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)
