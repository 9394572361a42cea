"""What a trained model is, read from its checkpoint alone: the card `vfdata model-info` prints.

A lab that is handed a `.ckpt` (or a run folder) needs to know, before it predicts on its own video,
what the model expects and what it has seen: the network and its symmetry views, the inputs (tracker,
points, token features, object frame, clip length, frame rate), the recordings it was trained and
validated on, the force range training covered (N; beyond it the model extrapolates and every estimate
says so), how its 90% band was calibrated (on how many validation frames), and how low the training
tissues hang (the lean, deg). Everything comes from what Lightning and `ForceRegressor` already store in
the checkpoint; the run folder's `metrics.json` adds the test figures where `vfdata experiment` or
`train.py test` wrote them. Nothing here loads the network: the card reads plain values only.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from vfdata.errors import InputError
from vfdata.manifest import load_manifest
from vfmodels.training.checkpoint import best_checkpoint, read_checkpoint

COMPONENTS = ("Fx", "Fy", "Fz")


def checkpoint_of(path: str | Path) -> tuple[Path, Path | None]:
    """The checkpoint a path names (a .ckpt, or a run folder's best) and its run folder (the one holding
    `checkpoints/`, None for a lone file)."""
    path = Path(path)
    if path.is_dir() and (path / "checkpoints").is_dir():
        return best_checkpoint(path / "checkpoints"), path
    if path.is_dir():
        return best_checkpoint(path), path.parent if path.name == "checkpoints" else None
    if not path.is_file():
        raise InputError(path, "checkpoint not found")
    return path, path.parent.parent if path.parent.name == "checkpoints" else None


def model_card(checkpoint: dict[str, Any], path: Path, run: Path | None = None) -> dict[str, Any]:
    """The card of a checkpoint's contents (`read_checkpoint`): plain values, JSON-ready. `run` adds the
    run folder's test figures (its metrics.json) when there are any. An InputError naming the file when
    it is not a ForceRegressor checkpoint or its entries are not what training writes."""
    if not isinstance(checkpoint.get("force_model"), dict):
        raise InputError(path, "not a ForceRegressor checkpoint (no 'force_model' entry)")
    try:
        return _card(checkpoint, path, run)
    except (AttributeError, TypeError, ValueError) as exc:  # entries of another shape: a damaged file
        raise InputError(path, f"damaged checkpoint: an entry is not what training writes ({exc})") from None


def _card(checkpoint: dict[str, Any], path: Path, run: Path | None) -> dict[str, Any]:
    force_model = checkpoint["force_model"]
    data = checkpoint.get("datamodule_hyper_parameters") or {}
    spec = data.get("spec") or {}
    state = checkpoint.get("ForceDataModule") or {}
    weights = checkpoint.get("state_dict") or {}
    band = force_model.get("band") or {}
    named = state.get("recordings")
    for key in ("recordings", "doubtful"):
        value = state.get(key)
        if value is not None and not (isinstance(value, dict) and all(isinstance(v, list) for v in value.values())):
            raise ValueError(f"{key} {value!r} are not lists by split or recording")
    return {
        "file": str(path),
        "size_mb": round(path.stat().st_size / 1e6, 2),
        "model": {
            "class": str(force_model.get("class_path", "")).rpartition(".")[2],
            "config": {k: v for k, v in (force_model.get("init_args") or {}).items() if _plain(v)},
            "weights": int(sum(v.numel() for k, v in weights.items()
                               if k.startswith("model.") and hasattr(v, "numel"))),
            "symmetry_turns": force_model.get("symmetry_turns", 0),
        },
        "training": {
            "epochs": int(checkpoint.get("epoch", -1)) + 1,
            "steps": checkpoint.get("global_step"),
            "lightning": checkpoint.get("pytorch-lightning_version"),
            **{k: v for k, v in (checkpoint.get("hyper_parameters") or {}).items() if k in ("lr", "weight_decay")},
            "manifest": data.get("manifest"),
            "recordings": named or _manifest_recordings(data.get("manifest")),
            "recordings_from": "checkpoint" if named else "manifest",
            "doubtful": state.get("doubtful"),
        },
        "inputs": {
            "tracker": state.get("tracker"),
            **{k: spec[k] for k in ("input", "features", "radius", "frame", "num_points", "clip_frames", "stride",
                                    "fps") if k in spec},
        },
        "force_range_n": _range(band),
        "band": {k: band[k] for k in ("coverage", "frames", "scale") if k in band} or None,
        "tissue_lean_deg": state.get("tissue_lean_deg"),
        "test": _test_figures(run),
    }


def card_text(card: dict[str, Any]) -> str:
    """The card as a person reads it: one line a fact, units named."""
    model, training, inputs = card["model"], card["training"], card["inputs"]
    config = ", ".join(f"{k} {v}" for k, v in model["config"].items())
    views = 2 * model["symmetry_turns"] if model["symmetry_turns"] else 1
    lines = [f"file:       {card['file']}  ({card['size_mb']} MB)",
             f"model:      {model['class']} ({config}); {model['weights']:,} weights; forces averaged over "
             f"{views} symmetry view{'s' if views > 1 else ''}",
             f"training:   {training['epochs']} epochs, {training['steps']} steps"
             + (f", lr {training['lr']:g}" if "lr" in training else "")
             + (f", Lightning {training['lightning']}" if training.get("lightning") else "")]
    recordings = training.get("recordings")
    if recordings and training.get("recordings_from") == "manifest":
        lines.append("recordings: as the training manifest lists them now (the checkpoint, from before "
                     "2026-12-07, does not name them)")
    if recordings:
        lines += [f"{split + ':':11} {len(ids)} recording{'s' if len(ids) != 1 else ''}: {', '.join(ids)}"
                  for split, ids in recordings.items()]
    else:
        lines.append("recordings: not named (a checkpoint from before 2026-12-07, its manifest gone)")
    if training.get("doubtful"):
        lines.append("doubtful:   trained or validated on although `vfdata process` judged them doubtful: " + ", ".join(
            f"{rid} ({', '.join(reasons)})" for rid, reasons in training["doubtful"].items()))
    if training.get("manifest"):
        lines.append(f"manifest:   {training['manifest']}")
    if inputs.get("input") == "tracks":
        tracker = inputs.get("tracker") or "an unnamed tracker"
        lines.append(f"inputs:     {inputs.get('num_points')} points tracked by {tracker}, tokens "
                     f"{inputs.get('features')}{' (r0 in tissue radii)' if inputs.get('radius') == 'tissue' else ''} "
                     f"in the {inputs.get('frame')} frame, clips of "
                     f"{inputs.get('clip_frames')} frames (stride {inputs.get('stride')}) at "
                     f"{inputs.get('fps', 0):.0f} fps")
    elif inputs.get("input"):
        lines.append(f"inputs:     {inputs['input']}, clips of {inputs.get('clip_frames')} frames at "
                     f"{inputs.get('fps', 0):.0f} fps")
    if card["force_range_n"]:
        lines.append("forces:     trained on " + ", ".join(
            f"{c} {lo:+.1f}..{hi:+.1f}" for c, (lo, hi) in zip(COMPONENTS, card["force_range_n"], strict=True))
            + " N; estimates beyond are marked")
    band = card["band"]
    if band:
        scale = ", ".join(f"{c} {s:.2f}" for c, s in zip(COMPONENTS, band.get("scale", ()), strict=False))
        lines.append(f"band:       {band.get('coverage', 0) * 100:.0f}% band calibrated on {band.get('frames')} "
                     f"validation frames (scale {scale} N)")
    else:
        lines.append("band:       none (no validation split when it was trained)")
    if card["tissue_lean_deg"]:
        lo, hi = card["tissue_lean_deg"]
        lines.append(f"tissues:    hang {lo:.1f}-{hi:.1f} deg below level (the lean; docs/models.md)")
    test = card["test"]
    if test:
        lines.append(f"test:       RMSE {test['rmse_n']:.3f} N, R2 {test['r2']:.3f} over {test['frames']} frames"
                     + (f" ({test['variant']}, seed {test['seed']})" if test.get("variant") else ""))
    return "\n".join(lines)


def read_model_card(path: str | Path) -> dict[str, Any]:
    """The card of a .ckpt file or a run folder (its best checkpoint and metrics.json)."""
    ckpt, run = checkpoint_of(path)
    return model_card(read_checkpoint(ckpt), ckpt, run)


def _manifest_recordings(manifest: str | None) -> dict[str, list[str]] | None:
    """The train and val ids of the manifest a checkpoint was trained with, where that file still reads
    (checkpoints from before they named their recordings); None otherwise."""
    if not manifest or not Path(manifest).is_file():
        return None
    try:
        manifest = load_manifest(manifest)
    except InputError:
        return None
    return manifest.ids(("train", "val"))


def _plain(value: Any) -> bool:
    return isinstance(value, (int, float, str, bool)) and value != ""


def _range(band: dict[str, Any]) -> list[list[float]] | None:
    low, high = band.get("train_min_n"), band.get("train_max_n")
    if low is None or high is None:
        return None
    return [[round(float(lo), 3), round(float(hi), 3)] for lo, hi in zip(low, high, strict=True)]


def _test_figures(run: Path | None) -> dict[str, Any] | None:
    """Pooled test RMSE (N) and R² of the run folder's metrics.json, None when it has none."""
    metrics = run / "metrics.json" if run is not None else None
    if metrics is None or not metrics.is_file():
        return None
    try:
        values = json.loads(metrics.read_text())
        pooled = values["pooled"]
        return {"rmse_n": float(pooled["rmse"]), "r2": float(pooled["r2"]), "frames": values.get("test_frames"),
                "variant": values.get("variant"), "seed": values.get("seed")}
    except (ValueError, KeyError, TypeError):
        raise InputError(metrics, "not the metrics of a test run (no pooled rmse and r2)") from None
