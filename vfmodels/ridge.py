"""A fast, closed-form force model on the same point tokens: the ridge rung of the attribution ladder
and a baseline that trains in seconds (bench/study_tokens.py measured the choices).

Per frame, the valid point tokens (standardised per channel) are pooled into their first and second
moments: the mean of each channel and the mean of every pairwise product (what a set model with a
quadratic per-point map and mean pooling can read). The frame's vector is joined with those of the
frames `lags` before it in the same gap-free run (causal, like the LSTM), and a ridge regression per
force component maps it to N; each component's strength is chosen on the validation split."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vfdata.clips.decode import Decoded
from vfdata.clips.tokens import mirror_tokens, segments

LAGS = (0, 5, 10, 15)
ALPHAS = tuple(float(a) for a in np.logspace(-2, 5, 15))


def pooled_moments(tokens: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(F, N, C) standardised tokens + (F, N) valid -> (F, C + C(C+1)/2): per-frame channel means and
    means of pairwise products (zeros for a frame with no valid point)."""
    w = valid.astype(np.float64)
    count = np.maximum(w.sum(axis=1, keepdims=True), 1.0)
    x = tokens.astype(np.float64) * w[..., None]
    first = x.sum(axis=1) / count
    i, j = np.triu_indices(tokens.shape[-1])
    second = np.einsum("fnc,fnd->fcd", x, tokens.astype(np.float64))[:, i, j] / count
    return np.concatenate([first, second], axis=1)


def with_lags(features: np.ndarray, times_ns: np.ndarray, lags: tuple[int, ...] = LAGS) -> np.ndarray:
    """Each frame's features joined with those `lags` frames earlier, clamped to its gap-free run."""
    index = np.arange(len(features))
    starts = np.zeros(len(features), dtype=np.int64)
    for start, stop in segments(times_ns):
        starts[start:stop] = start
    return np.concatenate([features[np.maximum(index - lag, starts)] for lag in lags], axis=1)


@dataclass
class RidgeForceModel:
    """Pooled-moment ridge regression from point tokens to (Fx, Fy, Fz) N (see the module docstring)."""

    lags: tuple[int, ...] = LAGS
    alphas: tuple[float, ...] = ALPHAS
    mirror: bool = False  # add training copies mirrored across the object's XZ plane
    token_mean: np.ndarray | None = field(default=None, repr=False)
    token_std: np.ndarray | None = field(default=None, repr=False)
    feature_mean: np.ndarray | None = field(default=None, repr=False)
    feature_std: np.ndarray | None = field(default=None, repr=False)
    weights: np.ndarray | None = field(default=None, repr=False)  # (D + 1, 3)
    chosen_alphas: list[float] = field(default_factory=list)

    def _features(self, decoded: Decoded, mirrored: bool = False) -> np.ndarray:
        tokens = mirror_tokens(decoded.inputs) if mirrored else decoded.inputs
        z = (tokens - self.token_mean) / self.token_std
        return with_lags(pooled_moments(z, decoded.valid), decoded.times_ns, self.lags)

    def _design(self, recordings: list[Decoded], train: bool) -> tuple[np.ndarray, np.ndarray]:
        xs, ys = [], []
        for d in recordings:
            for mirrored in ((False, True) if train and self.mirror else (False,)):
                xs.append(self._features(d, mirrored))
                ys.append(d.force_n * (np.array([1.0, -1.0, 1.0]) if mirrored else 1.0))
        x, y = np.concatenate(xs), np.concatenate(ys).astype(np.float64)
        known = np.isfinite(y).all(axis=1)
        return x[known], y[known]

    def fit(self, train: list[Decoded], val: list[Decoded]) -> RidgeForceModel:
        values = np.concatenate([d.inputs[d.valid] for d in train]).astype(np.float64)
        self.token_mean, self.token_std = values.mean(0), values.std(0) + 1e-6
        x, y = self._design(train, train=True)
        self.feature_mean, self.feature_std = x.mean(0), x.std(0) + 1e-9
        xs = np.c_[(x - self.feature_mean) / self.feature_std, np.ones(len(x))]
        xv, yv = self._design(val, train=False)
        xv = np.c_[(xv - self.feature_mean) / self.feature_std, np.ones(len(xv))]
        gram, rhs = xs.T @ xs, xs.T @ y
        penalty = np.eye(len(gram))
        penalty[-1, -1] = 0.0  # the intercept is not shrunk
        self.weights = np.zeros((len(gram), 3))
        self.chosen_alphas = []
        for k in range(3):
            best = None
            for alpha in self.alphas:
                w = np.linalg.solve(gram + alpha * len(x) * 1e-3 * penalty, rhs[:, k])
                rmse = float(np.sqrt(np.mean((xv @ w - yv[:, k]) ** 2)))
                if best is None or rmse < best[0]:
                    best = (rmse, alpha, w)
            self.weights[:, k] = best[2]
            self.chosen_alphas.append(best[1])
        return self

    def predict(self, decoded: Decoded) -> np.ndarray:
        """(F, 3) forces in N for every frame of a recording."""
        x = (self._features(decoded) - self.feature_mean) / self.feature_std
        return np.c_[x, np.ones(len(x))] @ self.weights
