"""Per-frame reference models for one recording split in time or at random: a constant predictor (the
training mean), ridge regression on the depth change from the first frame, and ridge on the masked
depth (docs/results.md, "Real recording: Gao et al. 2018"). Pure functions on arrays: depths (T, H, W)
mm with NaN unknown, masks (T, H, W) bool, forces (T, 3) N.

Ridge strengths are chosen on the validation frames; features are standardised on the training ones."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vfdata.clips.datamodule import random_parts
from vfmodels.evaluation.metrics import force_metrics

ALPHAS = tuple(10.0 ** np.arange(-2, 7))
FEATURE_SIZE = 32


def _resized(image: np.ndarray, size: int) -> np.ndarray:
    return cv2.resize(image.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA).ravel()


def depth_change_features(depths_mm: np.ndarray, size: int = FEATURE_SIZE) -> np.ndarray:
    """(T, size*size): each frame's depth minus the first frame's (mm; 0 where either is unknown),
    averaged down to size x size."""
    change = np.nan_to_num(np.asarray(depths_mm, np.float64) - np.asarray(depths_mm[0], np.float64), nan=0.0)
    return np.stack([_resized(frame, size) for frame in change])


def masked_depth_features(depths_mm: np.ndarray, masks: np.ndarray, size: int = FEATURE_SIZE) -> np.ndarray:
    """(T, size*size): each frame's depth inside its tissue mask, less the mask's median depth (so the
    shape, not the distance, is seen), 0 outside; averaged down to size x size."""
    rows = []
    for depth, mask in zip(depths_mm, masks, strict=True):
        inside = mask & np.isfinite(depth)
        frame = np.zeros(depth.shape, np.float64)
        if inside.any():
            frame[inside] = depth[inside] - np.median(depth[inside])
        rows.append(_resized(frame, size))
    return np.stack(rows)


@dataclass(frozen=True)
class RidgeModel:
    mean: np.ndarray  # (D,)
    scale: np.ndarray  # (D,)
    weights: np.ndarray  # (D, 3)
    bias: np.ndarray  # (3,)
    alpha: float

    def predict(self, features: np.ndarray) -> np.ndarray:
        return ((features - self.mean) / self.scale) @ self.weights + self.bias


def fit_ridge(x_train: np.ndarray, y_train: np.ndarray, x_val: np.ndarray, y_val: np.ndarray,
              alphas: tuple[float, ...] = ALPHAS) -> RidgeModel:
    """Ridge (N, D) -> (N, 3) with the strength of least validation RMSE (mean of the components)."""
    mean, scale = x_train.mean(axis=0), x_train.std(axis=0)
    scale = np.where(scale > 1e-9, scale, 1.0)
    z = (x_train - mean) / scale
    bias = y_train.mean(axis=0)
    # one SVD for every strength
    u, s, vt = np.linalg.svd(z, full_matrices=False)
    uty = u.T @ (y_train - bias)
    best = None
    for alpha in alphas:
        weights = vt.T @ ((s / (s ** 2 + alpha))[:, None] * uty)
        model = RidgeModel(mean, scale, weights, bias, float(alpha))
        rmse = float(np.sqrt(((model.predict(x_val) - y_val) ** 2).mean(axis=0)).mean())
        if best is None or rmse < best[0]:
            best = (rmse, model)
    return best[1]


def per_component_metrics(pred_n: np.ndarray, true_n: np.ndarray) -> dict[str, float]:
    """RMSE, NRMSE and R² per component (vfmodels.evaluation.metrics) plus MAE per component and overall (N)."""
    out = force_metrics(pred_n, true_n)
    mae = np.abs(np.asarray(pred_n) - np.asarray(true_n)).mean(axis=0)
    for comp, value in zip(("fx", "fy", "fz"), mae, strict=True):
        out[f"mae_{comp}"] = float(value)
    out["mae"] = float(mae.mean())
    return out


def temporal_indices(frames: dict[str, tuple[int, int]]) -> dict[str, np.ndarray]:
    """{split: frame indices} of [start, stop) ranges."""
    return {split: np.arange(*bounds) for split, bounds in frames.items()}


def random_indices(count: int, test_share: float = 0.2, val_share: float = 0.1, seed: int = 0) -> dict[str, np.ndarray]:
    """The original code's split: frames shuffled, `test_share` of them for test; `val_share` of the
    rest for choosing ridge strengths. Neighbouring frames (33 ms apart) land on both sides."""
    return random_parts(count, test_share, val_share, seed)


def run_baselines(features: dict[str, np.ndarray], force_n: np.ndarray,
                  splits: dict[str, np.ndarray]) -> tuple[dict[str, dict[str, float]], dict[str, np.ndarray]]:
    """Constant and one ridge per feature set on `splits` (train/val/test indices): test metrics per
    model, and test predictions per model."""
    train, val, test = splits["train"], splits["val"], splits["test"]
    metrics, predictions = {}, {}
    constant = np.repeat(force_n[train].mean(axis=0, keepdims=True), len(test), axis=0)
    metrics["constant"], predictions["constant"] = per_component_metrics(constant, force_n[test]), constant
    for name, x in features.items():
        model = fit_ridge(x[train], force_n[train], x[val], force_n[val])
        pred = model.predict(x[test])
        metrics[name] = {**per_component_metrics(pred, force_n[test]), "alpha": model.alpha}
        predictions[name] = pred
    return metrics, predictions
