"""A fast, closed-form force model on the same point tokens: the ridge rung of the attribution ladder
and a baseline that trains in seconds (bench/study_tokens.py measured the choices).

Per frame, the valid point tokens (standardised per channel) are pooled into their first and second
moments: the mean of each channel and the mean of every pairwise product (what a set model with a
quadratic per-point map and mean pooling can read). The frame's vector is joined with those of the
frames `lags` before it in the same gap-free run (causal, like the LSTM), and a ridge regression per
force component maps it to N. Each component's strength is chosen by leave-one-recording-out over the
training and validation recordings: one validation recording at the training orientation chose
strengths that transferred badly (docs/results.md, the ladder), a dozen folds choose steadily."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vfdata.clips.decode import Decoded
from vfdata.clips.tokens import segments, transform_tokens, turn_about_z

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
    # training copies turned about the object's Z axis by multiples of 90 deg: for pooled first and second
    # moments, four turns give the same fit as any finer set (bench/study_tokens.py, rotations)
    rotate: bool = False
    token_mean: np.ndarray | None = field(default=None, repr=False)
    token_std: np.ndarray | None = field(default=None, repr=False)
    feature_mean: np.ndarray | None = field(default=None, repr=False)
    feature_std: np.ndarray | None = field(default=None, repr=False)
    weights: np.ndarray | None = field(default=None, repr=False)  # (D + 1, 3)
    chosen_alphas: list[float] = field(default_factory=list)

    def _views(self) -> list[np.ndarray]:
        """The (3, 3) maps of the training copies (identity first)."""
        angles = np.deg2rad([0, 90, 180, 270]) if self.rotate else [0.0]
        return [turn_about_z(a, m) for m in ((False, True) if self.mirror else (False,)) for a in angles]

    def _features(self, decoded: Decoded, view: np.ndarray | None = None) -> np.ndarray:
        tokens = decoded.inputs if view is None else transform_tokens(decoded.inputs, view.astype(np.float32))
        z = (tokens - self.token_mean) / self.token_std
        return with_lags(pooled_moments(z, decoded.valid), decoded.times_ns, self.lags)

    def _design(self, decoded: Decoded, train: bool) -> tuple[np.ndarray, np.ndarray]:
        xs, ys = [], []
        for view in (self._views() if train else [np.eye(3)]):
            xs.append(self._features(decoded, view))
            ys.append(decoded.force_n @ view.T)
        x, y = np.concatenate(xs), np.concatenate(ys).astype(np.float64)
        known = np.isfinite(y).all(axis=1)
        return x[known], y[known]

    def _solve(self, gram: np.ndarray, rhs: np.ndarray, rows: int, alpha: float) -> np.ndarray:
        penalty = np.eye(len(gram))
        penalty[-1, -1] = 0.0  # the intercept is not shrunk
        return np.linalg.solve(gram + alpha * rows * 1e-3 * penalty, rhs)

    def fit(self, train: list[Decoded], val: list[Decoded]) -> RidgeForceModel:
        values = np.concatenate([transform_tokens(d.inputs[d.valid], v.astype(np.float32))
                                 for d in train for v in self._views()]).astype(np.float64)
        self.token_mean, self.token_std = values.mean(0), values.std(0) + 1e-6
        designs = [self._design(d, train=True) for d in train]
        x = np.concatenate([d[0] for d in designs])
        self.feature_mean, self.feature_std = x.mean(0), x.std(0) + 1e-9

        def standard(a: np.ndarray) -> np.ndarray:
            return np.c_[(a - self.feature_mean) / self.feature_std, np.ones(len(a))]

        parts = [(standard(x), y) for x, y in designs]
        grams = [(a.T @ a, a.T @ y, len(a)) for a, y in parts]
        gram, rhs, rows = (sum(g[k] for g in grams) for k in range(3))
        # folds: each training recording left out in turn (its mirrored copy with it), and validation
        folds = [(gram - g, rhs - r, rows - n, *self._design(d, train=False))
                 for (g, r, n), d in zip(grams, train, strict=True)] if len(train) > 1 else []
        folds += [(gram, rhs, rows, *self._design(d, train=False)) for d in val]
        self.weights = np.zeros((len(gram), 3))
        self.chosen_alphas = []
        for k in range(3):
            errors = [np.mean([np.mean((standard(xv) @ self._solve(g, r[:, k], n, alpha) - yv[:, k]) ** 2)
                               for g, r, n, xv, yv in folds]) for alpha in self.alphas]
            alpha = self.alphas[int(np.argmin(errors))]
            self.weights[:, k] = self._solve(gram, rhs[:, k], rows, alpha)
            self.chosen_alphas.append(alpha)
        return self

    def predict(self, decoded: Decoded) -> np.ndarray:
        """(F, 3) forces in N for every frame of a recording."""
        x = (self._features(decoded) - self.feature_mean) / self.feature_std
        return np.c_[x, np.ones(len(x))] @ self.weights
