"""How sure a force estimate is: a band per frame and component (Fx, Fy, Fz), calibrated so that the
stated share of frames (`COVERAGE`, 90%) lies inside it.

Two signals, both free at inference: the spread (N, population std) of the model's forces over the tube's
symmetry views (`ForceRegressor.symmetry_turns`), which the regressor computes anyway to average them,
and the size of the estimate itself, |F| per component (N: errors grow with the force). Per component
the band's half-width is

    half_width = scale * sqrt(1 + (weight * spread)^2 + (force_weight * |F|)^2)          (N)

`scale` (N), `weight` and `force_weight` (1/N) are calibrated on the validation split by split-conformal
scaling (`calibrate`): the weights are chosen on one half of the validation frames (alternate blocks of
`BLOCK_FRAMES`), each among 0 and multiples of 1 / its median there, as the pair whose band of the
stated coverage is narrowest there (both 0: a constant band); the scale is the conformal quantile, on
the other half, of |error| / sqrt(1 + ...): the ceil((n + 1) * coverage)-th smallest score of n frames.
So on frames exchangeable with validation's the band covers at least `coverage` (choosing the weights on
the frames that set the scale would not: on 30 frames the band then held 88%, tests/test_band.py). With
fewer than `MIN_SPLIT_FRAMES` frames the band is constant, its scale from all of them.

On views the model has not learnt the errors are larger than validation's, at the training view, and
the band covers less than it states: docs/results.md, "How sure", measures by how much. A third signal
speaks for them: how unlike the training frames a frame's input is, the Mahalanobis distance of its
embedding (the set encoder's output, `ForceRegressor.embedding_distance`) from the training frames'. It
cannot be calibrated on validation, where frames are as familiar as training's, so it is a rule, not a
weight: the band is stretched by `stretch` = max(1, distance / `distance_ref`), `distance_ref` the median
distance of the validation frames. Validation's own band hardly changes (half its frames are not stretched,
the rest a little); a frame twice as far from training as validation's typical one gets twice the band.
A frame farther than all but `UNFAMILIAR_SHARE` of validation's (`distance_limit`) is marked unlike
training (`unfamiliar`): of the 12 sweep seeds' test frames 6.2% were, and their RMSE was 2.22 N against
1.07 N elsewhere (docs/results.md, "How sure").

Beyond what training covered a model extrapolates, and no calibration on validation speaks for it:
`beyond_range` says how far (N) each component of an estimate lies outside the training forces' range
(per component, widened by `vfdata.split_forces.BEYOND_MARGIN` of it, the split report's rule), and such
frames are marked wherever a force goes.

Pure functions on arrays: the ones used per frame (`half_width`, `beyond_range`) take NumPy arrays or
torch tensors alike (the calibration's numbers as arrays of the same kind).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from vfdata.split_forces import BEYOND_MARGIN
from vfmodels.evaluation.metrics import force_metrics

COVERAGE = 0.9  # the stated share of frames inside the band
COMPONENTS = ("fx", "fy", "fz")
WEIGHT_STEPS = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)  # candidate weights, in units of 1 / the signal's median
MIN_FRAMES = 20  # validation frames below which no band is calibrated
MIN_SPLIT_FRAMES = 200  # validation frames below which the band is constant (too few to choose a weight)
SIMPLER_BY = 0.03  # a band with fewer signals is kept when at most this much wider (_narrowest_weights)
BLOCK_FRAMES = 16  # the halves that choose the weight and set the scale alternate in blocks of this many
UNFAMILIAR_SHARE = 0.01  # validation frames beyond `distance_limit`: the rest are "like training"


@dataclass(frozen=True)
class BandCalibration:
    """A band's calibration (module docstring): per component `scale` (N), `weight` (of the views' spread)
    and `force_weight` (of |F|) (1/N); the `coverage` it states, the validation `frames` it was
    calibrated on, and the training forces' range (`train_min_n`, `train_max_n`, N per component; None
    when unknown), and `distance_ref`, the validation frames' median embedding distance that `stretch`
    measures a frame's against (None: no stretch), and `distance_limit`, beyond which a frame is unlike
    training (`unfamiliar`; None: no mark). Plain values: it is stored in checkpoints
    (`ForceRegressor.on_save_checkpoint`)."""

    scale: tuple[float, float, float]
    weight: tuple[float, float, float]
    force_weight: tuple[float, float, float] = (0.0, 0.0, 0.0)
    coverage: float = COVERAGE
    frames: int = 0
    train_min_n: tuple[float, float, float] | None = None
    train_max_n: tuple[float, float, float] | None = None
    distance_ref: float | None = None
    distance_limit: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> BandCalibration:
        """Raises ValueError when `values` is not a calibration (the caller names the file)."""
        def triple(key: str, optional: bool = False) -> tuple[float, float, float] | None:
            value = values.get(key)
            if value is None and optional:
                return None
            if not isinstance(value, (list, tuple)) or len(value) != 3 or \
                    not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
                raise ValueError(f"band calibration: {key} {value!r} is not three numbers")
            return tuple(float(v) for v in value)

        coverage = values.get("coverage", COVERAGE)
        if not isinstance(coverage, (int, float)) or not 0 < coverage < 1:
            raise ValueError(f"band calibration: coverage {coverage!r} is not a share between 0 and 1")
        distances = {key: values.get(key) for key in ("distance_ref", "distance_limit")}
        for key, value in distances.items():
            if value is not None and (not isinstance(value, (int, float)) or isinstance(value, bool)
                                      or not 0 < value < math.inf):
                raise ValueError(f"band calibration: {key} {value!r} is not a positive distance")
        return cls(triple("scale"), triple("weight"), triple("force_weight", True) or (0.0, 0.0, 0.0),
                   float(coverage), int(values.get("frames", 0)), triple("train_min_n", True),
                   triple("train_max_n", True),
                   *(None if value is None else float(value) for value in distances.values()))

    def with_training_range(self, low_n, high_n) -> BandCalibration:
        return replace(self, train_min_n=tuple(float(v) for v in low_n), train_max_n=tuple(float(v) for v in high_n))


def conformal_quantile(scores: np.ndarray, coverage: float = COVERAGE) -> float:
    """The split-conformal quantile of `scores` (n,): the ceil((n + 1) * coverage)-th smallest (inf when
    that is beyond n: too few frames to state the coverage)."""
    scores = np.sort(np.asarray(scores, dtype=np.float64).reshape(-1))
    rank = math.ceil((len(scores) + 1) * coverage)
    return float(scores[rank - 1]) if rank <= len(scores) else math.inf


def signal(spread_n, force_n, weight, force_weight):
    """sqrt(1 + (weight * spread)^2 + (force_weight * |F|)^2): 1 for a small force the views agree on."""
    return (1.0 + (weight * spread_n) ** 2 + (force_weight * force_n) ** 2) ** 0.5


def half_width(spread_n, force_n, scale_n, weight, force_weight):
    """The band's half-width (N, the shape of `spread_n` (..., 3)) for the views' spread and the estimate
    `force_n` (..., 3) N: the estimate +- it is the band."""
    return scale_n * signal(spread_n, force_n, weight, force_weight)


def stretch(distance, distance_ref: float | None):
    """The band's factor for frames' embedding distances (NumPy array or torch tensor, any shape):
    max(1, distance / distance_ref); 1 where the distance is unknown (NaN) or there is no reference."""
    factor = distance / (math.inf if distance_ref is None else distance_ref)
    if hasattr(factor, "nan_to_num"):  # a torch tensor
        return factor.nan_to_num(1.0).clamp(min=1.0)
    return np.maximum(np.nan_to_num(factor, nan=1.0), 1.0)


def distance_scale(distance: np.ndarray | None) -> tuple[float | None, float | None]:
    """(`distance_ref`, `distance_limit`) from validation frames' embedding distances (M,): their median and
    the quantile that all but `UNFAMILIAR_SHARE` of them lie within; (None, None) when unknown."""
    seen = np.zeros(0) if distance is None else np.asarray(distance, dtype=np.float64).reshape(-1)
    seen = seen[np.isfinite(seen)]
    if not len(seen) or np.median(seen) <= 0:
        return None, None
    reference, limit = np.quantile(seen, [0.5, 1 - UNFAMILIAR_SHARE])
    return float(reference), float(limit)


def unfamiliar_metrics(pred_n: np.ndarray, true_n: np.ndarray, distance: np.ndarray, limit: float | None
                       ) -> dict[str, float]:
    """Of test frames (M, 3) N with their distances (M,): the share whose input is unlike training's
    (beyond `limit`), the RMSE there and elsewhere (N, mean of the components; NaN without frames)."""
    def rmse(rows: np.ndarray) -> float:
        return force_metrics(pred_n[rows], true_n[rows])["rmse"] if rows.any() else math.nan

    unlike = _beyond(distance, limit)
    return {"share": float(unlike.mean()) if len(unlike) else math.nan, "frames": int(unlike.sum()),
            "rmse": rmse(unlike), "rmse_rest": rmse(~unlike)}


def unfamiliar(distance: np.ndarray, calibration: BandCalibration | None) -> np.ndarray:
    """Frames (the shape of `distance`) whose embedding lies farther from training's than all but
    `UNFAMILIAR_SHARE` of validation's (False where unknown, or without a limit): `unlikeness` above 1."""
    return _beyond(distance, None if calibration is None else calibration.distance_limit)


def unlikeness(distance: np.ndarray, calibration: BandCalibration | None) -> np.ndarray:
    """How unlike training's each frame's input is: its embedding distance over `distance_limit` (> 1:
    `unfamiliar`), NaN where the distance is unknown or there is no limit (`/force/estimate/unlike`)."""
    return _over_limit(distance, None if calibration is None else calibration.distance_limit)


def _over_limit(distance: np.ndarray, limit: float | None) -> np.ndarray:
    distance = np.asarray(distance, dtype=np.float64)
    return distance / limit if limit else np.full(distance.shape, np.nan)


def _beyond(distance: np.ndarray, limit: float | None) -> np.ndarray:
    """distance over limit above 1, False where the distance is unknown (NaN) or there is no limit."""
    with np.errstate(invalid="ignore"):
        return _over_limit(distance, limit) > 1.0


def calibrate(pred_n: np.ndarray, true_n: np.ndarray, spread_n: np.ndarray, coverage: float = COVERAGE,
              distance: np.ndarray | None = None) -> BandCalibration | None:
    """Split-conformal calibration on validation frames (module docstring): forces (M, 3) N predicted
    and measured, the views' spread (M, 3) N, and the frames' embedding distances (M,) when the model
    has a reference (their median is `distance_ref`). None with fewer than `MIN_FRAMES` frames with a
    force."""
    pred, true, spread = (np.asarray(a, dtype=np.float64).reshape(-1, 3) for a in (pred_n, true_n, spread_n))
    known = np.isfinite(true).all(axis=1) & np.isfinite(pred).all(axis=1) & np.isfinite(spread).all(axis=1)
    if known.sum() < max(MIN_FRAMES, math.ceil(1 / (1 - coverage))):
        return None
    error, spread, size = np.abs(pred - true)[known], spread[known], np.abs(pred)[known]
    if len(error) >= MIN_SPLIT_FRAMES:
        choose = (np.arange(len(error)) // BLOCK_FRAMES) % 2 == 0
        weights = [_narrowest_weights(error[choose, c], spread[choose, c], size[choose, c], coverage)
                   for c in range(3)]
        scaled = ~choose
    else:
        weights, scaled = [(0.0, 0.0)] * 3, np.ones(len(error), bool)
    scales = [conformal_quantile(error[scaled, c] / signal(spread[scaled, c], size[scaled, c], *weights[c]), coverage)
              for c in range(3)]
    reference, limit = distance_scale(None if distance is None else np.asarray(distance).reshape(-1)[known])
    return BandCalibration(tuple(scales), tuple(w[0] for w in weights), tuple(w[1] for w in weights),
                           float(coverage), int(known.sum()), distance_ref=reference, distance_limit=limit)


def _narrowest_weights(error: np.ndarray, spread: np.ndarray, size: np.ndarray, coverage: float
                       ) -> tuple[float, float]:
    """The candidate weights (of the spread, of |F|; 1/N) whose band of the stated coverage is narrowest
    on these frames."""
    def candidates(values: np.ndarray) -> list[float]:
        typical = float(np.median(values))
        return [0.0] + ([s / typical for s in WEIGHT_STEPS] if typical > 1e-9 else [])

    pairs = list(itertools.product(candidates(spread), candidates(size)))
    widths = []
    for weight, force_weight in pairs:
        s = signal(spread, size, weight, force_weight)
        widths.append(conformal_quantile(error / s, coverage) * float(s.mean()))
    # A signal is taken only when it narrows the band by more than SIMPLER_BY: chosen among 49 pairs on a
    # few hundred frames, one that does nothing still narrows it a little by chance, and widens it elsewhere.
    enough = [i for i, w in enumerate(widths) if w <= min(widths) * (1 + SIMPLER_BY)]
    best = min(enough, key=lambda i: (sum(v > 0 for v in pairs[i]), widths[i]))
    return pairs[best]


def beyond_range(force_n, low_n, high_n, margin: float = BEYOND_MARGIN):
    """How far (N, signed: below < 0 < above, 0 inside) each component of `force_n` (..., 3) lies beyond
    the range [low, high] widened on each side by `margin` of its width (the split report's rule)."""
    slack = margin * (high_n - low_n)
    lo, hi = low_n - slack, high_n + slack
    below = force_n - lo
    above = force_n - hi
    return below * (below < 0) + above * (above > 0)


def band_metrics(pred_n: np.ndarray, true_n: np.ndarray, half_width_n: np.ndarray) -> dict[str, float]:
    """Frames (M, 3) N -> {"coverage_fx": share of frames whose force lies inside the band, "half_width_fx":
    mean half-width (N), ..., "coverage", "half_width": the means over the three components}; NaN for a
    component whose band is unknown (not calibrated)."""
    pred, true, half = (np.asarray(a, dtype=np.float64).reshape(-1, 3) for a in (pred_n, true_n, half_width_n))
    known = np.isfinite(true).all(axis=1)
    pred, true, half = pred[known], true[known], half[known]
    out: dict[str, float] = {}
    with np.errstate(invalid="ignore"):
        inside = np.abs(pred - true) <= half
        for c, name in enumerate(COMPONENTS):
            calibrated = bool(len(half)) and bool(np.isfinite(half[:, c]).all())
            out[f"coverage_{name}"] = float(inside[:, c].mean()) if calibrated else math.nan
            out[f"half_width_{name}"] = float(half[:, c].mean()) if calibrated else math.nan
    out["coverage"] = float(np.mean([out[f"coverage_{c}"] for c in COMPONENTS]))
    out["half_width"] = float(np.mean([out[f"half_width_{c}"] for c in COMPONENTS]))
    return out


def grouped_band_metrics(pred_n: np.ndarray, true_n: np.ndarray, half_width_n: np.ndarray, groups: np.ndarray
                         ) -> dict[str, dict]:
    """{"pooled": band_metrics over all frames, "groups": {group (e.g. view, deg): band_metrics}}."""
    groups = np.asarray(groups).reshape(-1)
    pred, true, half = (np.asarray(a, dtype=np.float64).reshape(-1, 3) for a in (pred_n, true_n, half_width_n))
    return {"pooled": band_metrics(pred, true, half),
            "groups": {g.item(): band_metrics(pred[groups == g], true[groups == g], half[groups == g])
                       for g in np.unique(groups)}}


def describe(calibration: BandCalibration | None) -> str:
    """One line for logs and metadata."""
    if calibration is None:
        return "no band (not calibrated)"
    parts = [f"{n} {s:.3g} N (spread x{w:.3g}, |F| x{f:.3g})" for n, s, w, f in
             zip(("Fx", "Fy", "Fz"), calibration.scale, calibration.weight, calibration.force_weight, strict=True)]
    stretched = "" if calibration.distance_ref is None else \
        f"; stretched beyond embedding distance {calibration.distance_ref:.3g}"
    return f"{calibration.coverage:.0%} band on {calibration.frames} validation frames: " + ", ".join(parts) + stretched


def format_band_table(result: dict[str, dict], calibration: BandCalibration | None = None) -> str:
    """Plain text of `grouped_band_metrics`: coverage and mean half-width per component, pooled and per group."""
    if calibration is None and not np.isfinite(result["pooled"]["coverage"]):
        return "band: none (the model has no calibration: no validation split, or too few frames)"
    stated = f"{calibration.coverage:.0%}" if calibration is not None else "stated"
    lines = [f"band ({stated}): coverage / mean half-width N" + f"{'Fx':>18}{'Fy':>18}{'Fz':>18}{'avg':>18}"]
    rows = [("pooled", result["pooled"])] + [(f"{g}", m) for g, m in result["groups"].items()]
    for label, m in rows:
        cells = [f"{m['coverage' + s]:.0%} / {m['half_width' + s]:.3f}" for s in ("_fx", "_fy", "_fz", "")]
        lines.append(f"{label:>43}" + "".join(f"{c:>18}" for c in cells))
    return "\n".join(lines)
