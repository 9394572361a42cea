"""Feature statistics of a LeRobot dataset (what policies normalise with): per feature `min`, `max`,
`mean`, `std`, `count` and the quantiles `q01` `q10` `q50` `q90` `q99`, over an episode's frames
and then over the dataset. Numbers over every frame; images per colour channel (shape (3, 1, 1),
RGB in [0, 1]) over a sample of each episode's frames. Pure functions on arrays."""

from __future__ import annotations

import warnings

import numpy as np

QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
IMAGE_SAMPLES = 100  # frames of an episode its image statistics are taken from, at most
IMAGE_WIDTH = 160  # ... each reduced to about this width


def feature_stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """Statistics over the first axis of (frames, *shape) values, NaN left out (an estimate missing on
    some frames). A value that is NaN on every frame has NaN statistics."""
    data = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(data)
    count = np.array([len(data)])
    if finite.all():
        stats = {"min": data.min(0), "max": data.max(0), "mean": data.mean(0), "std": data.std(0),
                 **{name: np.quantile(data, q, axis=0) for name, q in QUANTILES.items()}}
    else:
        with np.errstate(all="ignore"), _quiet():
            stats = {"min": np.nanmin(data, 0), "max": np.nanmax(data, 0), "mean": np.nanmean(data, 0),
                     "std": np.nanstd(data, 0), **{name: np.nanquantile(data, q, axis=0)
                                                   for name, q in QUANTILES.items()}}
    return {**stats, "count": count}


def image_sample(frames: int) -> np.ndarray:
    """Which of an episode's frames its image statistics use: at most IMAGE_SAMPLES, evenly spread."""
    return np.unique(np.linspace(0, frames - 1, min(frames, IMAGE_SAMPLES)).round().astype(int))


def reduced(rgb: np.ndarray) -> np.ndarray:
    """An (H, W, 3) image taken every k-th pixel, k such that it is about IMAGE_WIDTH wide."""
    step = max(1, rgb.shape[1] // IMAGE_WIDTH)
    return rgb[::step, ::step]


def image_stats(sampled_rgb: np.ndarray) -> dict[str, np.ndarray]:
    """Per-channel statistics (3, 1, 1) in [0, 1] of (n, H, W, 3) uint8 RGB frames."""
    pixels = np.asarray(sampled_rgb, dtype=np.float64).reshape(-1, 3) / 255.0
    stats = {k: v.reshape(3, 1, 1) for k, v in feature_stats(pixels).items() if k != "count"}
    return {**stats, "count": np.array([len(sampled_rgb)])}


def aggregate(per_episode: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """A feature's statistics over episodes: extremes, the pooled mean and standard deviation (each
    episode weighted by its count), and count-weighted means of the quantiles (an approximation: the
    exact quantiles would need every value again)."""
    counts = np.array([float(s["count"][0]) for s in per_episode])
    total = counts.sum()
    weights = counts / total

    def weighted(key: str) -> np.ndarray:
        stacked = np.stack([s[key] for s in per_episode])
        return np.tensordot(weights, stacked, axes=1)

    mean = weighted("mean")
    spread = np.stack([s["std"] ** 2 + (s["mean"] - mean) ** 2 for s in per_episode])
    return {"min": np.min(np.stack([s["min"] for s in per_episode]), axis=0),
            "max": np.max(np.stack([s["max"] for s in per_episode]), axis=0),
            "mean": mean, "std": np.sqrt(np.tensordot(weights, spread, axes=1)),
            "count": np.array([int(total)]), **{name: weighted(name) for name in QUANTILES}}


def to_json(stats: dict[str, dict[str, np.ndarray]]) -> dict:
    """{feature: {stat: nested lists}} (NaN as null: JSON has no NaN)."""
    def plain(value: np.ndarray):
        array = np.asarray(value)
        return np.where(np.isfinite(array), array, None).tolist() if array.dtype.kind == "f" else array.tolist()

    return {feature: {k: plain(v) for k, v in values.items()} for feature, values in stats.items()}


class _quiet:
    """numpy's "All-NaN slice" warnings off: a value missing on every frame is expected (NaN stats)."""

    def __enter__(self):
        self._catch = warnings.catch_warnings()
        self._catch.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc):
        self._catch.__exit__(*exc)
