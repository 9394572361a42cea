"""Figures of an experiment and of a prediction: Fig. 5 (force distributions), Fig. 6 (tracked points
at a force peak), Fig. 7 (force against time), training curves, first frames, and the force plot
of `vfdata predict`. Pure functions from arrays to PNG files (matplotlib, Agg)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display is needed, or wanted on a cluster node
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402
from scipy.stats import gaussian_kde  # noqa: E402

from vfmodels.evaluation.metrics import COMPONENTS  # noqa: E402
from vfmodels.reports.tables import check_predictions, training_summary  # noqa: E402


def plot_force_curves(predictions: Mapping[str, np.ndarray], path: str | Path, fps: float = 30.0,
                      title: str = "", max_recordings: int | None = None) -> Path:
    """Fig. 7: measured (solid) and predicted (dashed) Fx, Fy, Fz against time, one column per test
    orientation (its first recording, or `max_recordings` of them one after another)."""
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
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def force_kde(samples: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Gaussian kernel density (Scott's bandwidth) of 1-D `samples` on `grid`; a degenerate sample
    (fewer than two distinct values) gives a narrow spike of unit area at its value."""
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
    fig, ax = plt.subplots(figsize=(8, 4.2))
    palette = plt.get_cmap("tab10" if len(curves) <= 10 else "tab20")  # a full grid has 11 or more runs
    for k, (label, run) in enumerate(curves.items()):
        colour = palette(k % palette.N)
        epochs = np.asarray(run["epoch"])
        seconds = float(np.nansum(run["time/epoch_s"]))
        took = f"{seconds / 60:.0f} min" if seconds >= 90 else f"{seconds:.0f} s"
        ax.plot(epochs, run["train/loss_epoch"], color=colour, alpha=0.5, linestyle="--")
        val = np.asarray(run["val/loss"], dtype=np.float64)
        ax.plot(epochs, val, color=colour, label=f"{label}: {len(epochs)} epochs, {took}")
        best = training_summary(run)["best_epoch"]
        if best is not None:
            ax.plot(best, val[epochs == best][0], "o", color=colour)
    ax.set_xlabel("epoch")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
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


def plot_force_series(force_n: np.ndarray, path: str | Path, frame_index: np.ndarray | None = None,
                      measured_n: np.ndarray | None = None, title: str = "", band_n: np.ndarray | None = None,
                      beyond_n: np.ndarray | None = None, coverage: float | None = None,
                      unfamiliar: np.ndarray | None = None) -> Path:
    """`vfdata predict`'s plot: Fx, Fy, Fz (N) against the frame index, one panel each. With the
    recording's measured force: measured solid in colour, estimated dashed black (as Fig. 7), and
    each panel's RMSE in its label. With `band_n` (T, 3) N, the band's half-width: the estimate +- it
    shaded (and, with a measured force, the share of frames inside it); with `beyond_n` (T, 3) N, the
    frames whose component lies beyond the training range marked on the panel's lower edge; with
    `unfamiliar` (T,) bool, the frames whose input is unlike training's marked on its upper edge."""
    force = np.asarray(force_n, dtype=np.float64).reshape(-1, 3)
    index = np.arange(len(force)) if frame_index is None else np.asarray(frame_index)
    band = None if band_n is None else np.asarray(band_n, dtype=np.float64).reshape(-1, 3)
    stated = f"{coverage:.0%} band" if coverage is not None else "band"
    fig, axes = plt.subplots(3, 1, figsize=(10, 6.5), sharex=True)
    for k, (ax, comp, colour) in enumerate(zip(axes, COMPONENTS, ("tab:red", "tab:green", "tab:blue"), strict=True)):
        label = "estimated"
        if band is not None and np.isfinite(band[:, k]).any():
            band_label = stated
            if measured_n is not None:
                measured = np.asarray(measured_n, dtype=np.float64)[:, k]
                known = np.isfinite(measured) & np.isfinite(band[:, k])
                if known.any():
                    inside = np.abs(force[known, k] - measured[known]) <= band[known, k]
                    band_label += f" (holds {inside.mean():.0%} of the measured)"
            ax.fill_between(index, force[:, k] - band[:, k], force[:, k] + band[:, k], color="0.5", alpha=0.3,
                            lw=0, label=band_label)
        if measured_n is not None:
            measured = np.asarray(measured_n, dtype=np.float64)[:, k]
            known = np.isfinite(measured) & np.isfinite(force[:, k])
            ax.plot(index, measured, color=colour, lw=1.2, label="measured")
            if known.any():
                label += f" (RMSE {np.sqrt(np.mean((force[known, k] - measured[known]) ** 2)):.2f} N)"
            ax.plot(index, force[:, k], color="black", lw=1.0, ls="--", label=label)
        else:
            ax.plot(index, force[:, k], color=colour, lw=1.2, label=label)
        if beyond_n is not None:
            beyond = np.asarray(beyond_n, dtype=np.float64).reshape(-1, 3)[:, k] != 0
            if beyond.any():
                ax.plot(index[beyond], np.full(int(beyond.sum()), 0.02), "|", color="tab:orange", ms=8,
                        transform=ax.get_xaxis_transform(), label=f"beyond training ({beyond.sum()} frames)")
        if unfamiliar is not None and np.asarray(unfamiliar).any():
            unlike = np.asarray(unfamiliar, bool).reshape(-1)
            ax.plot(index[unlike], np.full(int(unlike.sum()), 0.98), "|", color="tab:purple", ms=8,
                    transform=ax.get_xaxis_transform(), label=f"input unlike training ({unlike.sum()} frames)")
        ax.set_ylabel(f"F{comp[1]} (N)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("frame")
    fig.suptitle(title or "estimated force (object frame)")
    return save_figure(fig, path)
