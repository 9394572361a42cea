"""Tables of an experiment (docs/experiments.md): pure functions from arrays and dicts to text.
Nothing here reads MCAP or runs a model; `vfmodels.experiment` gathers the inputs.

Force tables (the paper's Tables I and II). For every model variant and seed, the test frames give
RMSE (N), NRMSE and R^2 per component (Fx, Fy, Fz) and their average, pooled over all test frames,
and the same per test orientation. A table cell is the pooled value averaged over seeds, +- the
standard deviation across test orientations (also averaged over seeds; "n/a" with one orientation);
the CSV keeps the spread across seeds as well.

Band table (`band_markdown`): per model and test orientation, the stated 90% band's coverage and mean
half-width against the RMSE there (`vfmodels.evaluation.band`).

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
from scipy.stats import spearmanr

from vfmodels.evaluation.band import grouped_band_metrics
from vfmodels.evaluation.metrics import COMPONENTS, grouped_force_metrics

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
    `vfmodels.evaluation.metrics.grouped_force_metrics`, grouped by orientation (deg); with "band" when the frames
    carry a calibrated band (`vfmodels.evaluation.band.grouped_band_metrics`: coverage and mean half-width)."""
    check_predictions(predictions)
    known = np.isfinite(predictions["true"]).all(axis=1) & np.isfinite(predictions["pred"]).all(axis=1)
    orientation = np.asarray(predictions["orientation_deg"], dtype=np.float64)[known]
    pred, true = np.asarray(predictions["pred"])[known], np.asarray(predictions["true"])[known]
    result = grouped_force_metrics(pred, true, orientation)
    half = np.asarray(predictions["band"])[known] if "band" in predictions else None
    if half is not None and len(half) and np.isfinite(half).all():
        result["band"] = grouped_band_metrics(pred, true, half, orientation)
    return result


def band_markdown(runs: Mapping[str, Sequence[Mapping]], labels: Mapping[str, str], dataset: str,
                  val_recordings: int | None = None) -> str:
    """How sure each model is at each test orientation: the stated band's coverage and mean half-width
    (N) per component against the RMSE there, means over seeds, and Spearman's correlation between the
    per-view half-width and RMSE over every seed's views; with `val_recordings`, how many recordings the
    band was calibrated on. Empty when no run has a band."""
    rows = {name: [r for r in found if "band" in r] for name, found in runs.items()}
    rows = {name: found for name, found in rows.items() if found}
    if not rows:
        return ""
    lines = [f"**How sure on {dataset}: the 90% band at each test orientation** (coverage: share of test frames "
             "inside the band; half-width: its mean +- in N; RMSE in N; means over seeds)", "",
             "| model | view | seeds | coverage Fx / Fy / Fz | half-width Fx / Fy / Fz | RMSE Fx / Fy / Fz "
             "| half-width / RMSE |", "| --- | --- | ---: | ---: | ---: | ---: | ---: |"]
    notes = []
    for name, found in rows.items():
        angles = sorted({float(a) for r in found for a in r["band"]["groups"]})
        for view in ["pooled", *angles]:
            cells = [_band_cells(r, view) for r in found]
            cells = [c for c in cells if c is not None]
            if not cells:
                continue
            mean = np.mean(cells, axis=0)
            ratio = mean[3:6].mean() / mean[6:9].mean() if mean[6:9].mean() > 0 else np.nan
            lines.append(f"| {labels.get(name, name)} | {view if view == 'pooled' else f'{view:g}°'} | {len(cells)} | "
                         + " / ".join(f"{v:.0%}" for v in mean[:3]) + " | "
                         + " / ".join(f"{v:.2f}" for v in mean[3:6]) + " | "
                         + " / ".join(f"{v:.2f}" for v in mean[6:9]) + f" | {ratio:.2f} |")
        views = [_band_cells(r, float(a)) for r in found for a in r["band"]["groups"]]
        width = [c[3:6].mean() for c in views if c is not None]
        rmse = [c[6:9].mean() for c in views if c is not None]
        if len(width) >= 3:
            rho = float(spearmanr(width, rmse).statistic)
            notes.append(f"{labels.get(name, name)}: Spearman(half-width, RMSE) over {len(width)} views {rho:.2f}")
        unlike = [r["unfamiliar"] for r in found if "unfamiliar" in r]
        if unlike:
            share = np.mean([u["share"] for u in unlike])
            notes.append(f"{labels.get(name, name)}: {share:.1%} of test frames have an input unlike training's "
                         "(embedding beyond 99% of validation's), RMSE there "
                         + ", ".join(f"{u['rmse']:.2f}" for u in unlike) + " N against "
                         + ", ".join(f"{u['rmse_rest']:.2f}" for u in unlike) + " N elsewhere (per seed)")
    if val_recordings == 1:
        # Measured on fresh simulated tissues (docs/results.md, "Three validation tissues"): one validation
        # tissue is one draw of the tissue-to-tissue gain that dominates the error on a new specimen.
        notes.append("The band was calibrated on one validation recording: its coverage and the validation RMSE "
                     "speak for that one tissue; on new specimens validate on 3 or more (docs/experiments.md, "
                     "\"How many tissues to record\")")
    elif val_recordings:
        notes.append(f"The band was calibrated on {val_recordings} validation recordings, pooled")
    return "\n".join(lines + ([""] + notes if notes else [])) + "\n"


def _band_cells(run: Mapping, view: float | str) -> np.ndarray | None:
    """(coverage x3, half-width x3, RMSE x3) of one run at a view ("pooled" or degrees), None if absent."""
    if view == "pooled":
        band, force = run["band"]["pooled"], run["pooled"]
    else:
        band = next((m for k, m in run["band"]["groups"].items() if float(k) == view), None)
        force = next((m for k, m in run["groups"].items() if float(k) == view), None)
        if band is None or force is None:
            return None
    return np.array([band[f"coverage_{c}"] for c in COMPONENTS] + [band[f"half_width_{c}"] for c in COMPONENTS]
                    + [force[f"rmse_{c}"] for c in COMPONENTS])


def transfer_markdown(runs: Mapping[str, Sequence[Mapping]], labels: Mapping[str, str], dataset: str) -> str:
    """How each model's error at every test orientation compares with its error on the validation
    recordings (the training orientation): avg RMSE (N), means over the seeds that logged validation;
    the last column is the worst orientation's ratio to validation. Empty when no run has "val"."""
    rows = {name: [r for r in found if "val" in r] for name, found in runs.items()}
    rows = {name: found for name, found in rows.items() if found}
    if not rows:
        return ""
    angles = sorted({float(a) for found in rows.values() for r in found for a in r["groups"]})
    lines = [f"**Transfer on {dataset}: avg RMSE (N) on the validation recordings and at each test orientation**",
             "", "| model | seeds | validation | " + " | ".join(f"{a:g}°" for a in angles)
             + " | worst / validation |", "| --- | ---: | ---: |" + " ---: |" * (len(angles) + 1)]
    for name, found in rows.items():
        val = float(np.mean([r["val"]["rmse"] for r in found]))
        per = [np.mean([r["groups"][k]["rmse"] for r in found for k in r["groups"] if float(k) == a] or [np.nan])
               for a in angles]
        worst = np.nanmax(per) / val if val > 0 else np.nan
        lines.append(f"| {labels.get(name, name)} | {len(found)} | {val:.3f} | "
                     + " | ".join("–" if not np.isfinite(v) else f"{v:.3f}" for v in per) + f" | {worst:.2f} |")
    return "\n".join(lines) + "\n"


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
        "orientations": max(len(r.get("groups", {})) for r in runs),
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
                spread = _fmt(agg["orientation_std"][key]) if agg.get("orientations", 2) > 1 else "n/a"
                cells.append(f"{_fmt(agg['value'][key])} ± {spread}")
            name = labels.get(variant, variant) if i == 0 else ""
            lines.append(f"| {name} | {metric_label} | " + " | ".join(cells) + " |")
    seeds = sorted({agg["seeds"] for agg in table.values()})
    lines += ["", f"Pooled over all test frames ± std across test orientations; mean over "
                  f"{'/'.join(map(str, seeds))} seed(s)."]
    trained = [f"{labels.get(variant, variant)} {_epochs_text(agg)}" for variant, agg in table.items()
               if _has_training(agg)]
    if trained:
        lines.append(f"Epochs trained (epoch of the tested checkpoint, counted from 0 as in the checkpoint names; "
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


