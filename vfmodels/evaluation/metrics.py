"""Force-estimation metrics of the paper's Tables I and II: RMSE (N), NRMSE and R^2, per component
(Fx, Fy, Fz) and averaged over the three; pooled over all test frames, and mean +- std across test
orientations.

NRMSE divides each component's RMSE by the range (max - min) of that component's ground truth over
the whole evaluated set, also for the per-orientation figures, so that they share one scale.
"""

from __future__ import annotations

import numpy as np

COMPONENTS = ("fx", "fy", "fz")


def force_metrics(pred_n: np.ndarray, true_n: np.ndarray, range_n: np.ndarray | None = None) -> dict[str, float]:
    """pred_n, true_n (M, 3) forces in N -> {"rmse_fx": ..., "nrmse_fx": ..., "r2_fx": ..., "rmse": mean
    of the three, ...}. range_n (3,) is the ground-truth range for NRMSE; by default that of true_n.
    A component with zero variance (or range) gets R^2 (or NRMSE) = nan."""
    pred = np.asarray(pred_n, dtype=np.float64).reshape(-1, 3)
    true = np.asarray(true_n, dtype=np.float64).reshape(-1, 3)
    if pred.shape != true.shape or len(true) == 0:
        raise ValueError(f"need matching non-empty (M, 3) arrays, got {pred.shape} and {true.shape}")
    if range_n is None:
        range_n = true.max(axis=0) - true.min(axis=0)
    range_n = np.asarray(range_n, dtype=np.float64)
    sq_err = ((pred - true) ** 2).sum(axis=0)
    rmse = np.sqrt(sq_err / len(true))
    ss_tot = ((true - true.mean(axis=0)) ** 2).sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        nrmse = np.where(range_n > 0, rmse / range_n, np.nan)
        r2 = np.where(ss_tot > 0, 1.0 - sq_err / ss_tot, np.nan)
    out: dict[str, float] = {}
    for name, values in (("rmse", rmse), ("nrmse", nrmse), ("r2", r2)):
        for comp, value in zip(COMPONENTS, values, strict=True):
            out[f"{name}_{comp}"] = float(value)
        out[name] = float(np.mean(values))
    return out


def grouped_force_metrics(
    pred_n: np.ndarray, true_n: np.ndarray, groups: np.ndarray
) -> dict[str, dict[str, float]]:
    """Metrics pooled over all frames, per group (e.g. orientation in degrees), and their mean and
    (population) std across groups. Returns {"pooled": {...}, "mean": {...}, "std": {...},
    "groups": {group: {...}}}; NRMSE everywhere uses the pooled ground-truth range."""
    pred = np.asarray(pred_n, dtype=np.float64).reshape(-1, 3)
    true = np.asarray(true_n, dtype=np.float64).reshape(-1, 3)
    groups = np.asarray(groups).reshape(-1)
    if len(groups) != len(true):
        raise ValueError(f"{len(groups)} group labels for {len(true)} frames")
    range_n = true.max(axis=0) - true.min(axis=0)
    per_group = {
        g.item(): force_metrics(pred[groups == g], true[groups == g], range_n) for g in np.unique(groups)
    }
    keys = next(iter(per_group.values())).keys()
    table = np.array([[m[k] for k in keys] for m in per_group.values()])
    return {
        "pooled": force_metrics(pred, true, range_n),
        "mean": dict(zip(keys, table.mean(axis=0).tolist(), strict=True)),
        "std": dict(zip(keys, table.std(axis=0).tolist(), strict=True)),
        "groups": per_group,
    }


def format_table(result: dict[str, dict[str, float]]) -> str:
    """A plain-text table like the paper's: rows RMSE (N), NRMSE, R^2; columns Fx, Fy, Fz, mean;
    pooled values and, where there are several groups, mean +- std across groups."""
    lines = [f"{'':8}{'Fx':>22}{'Fy':>22}{'Fz':>22}{'avg':>22}"]
    several = len(result.get("groups", {})) > 1
    for name, label in (("rmse", "RMSE N"), ("nrmse", "NRMSE"), ("r2", "R^2")):
        cells = []
        for suffix in ("_fx", "_fy", "_fz", ""):
            key = name + suffix
            cell = f"{result['pooled'][key]:.3f}"
            if several:
                cell += f" ({result['mean'][key]:.3f}+-{result['std'][key]:.3f})"
            cells.append(f"{cell:>22}")
        lines.append(f"{label:8}" + "".join(cells))
    if several:
        lines.append("pooled over all frames (mean +- std across groups: " +
                     ", ".join(str(g) for g in result["groups"]) + ")")
    return "\n".join(lines)
