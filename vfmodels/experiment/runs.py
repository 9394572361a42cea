"""A finished run's folder: `OUT/runs/<variant>/seed<k>/` with predictions.npz (the test frames:
recording, orientation_deg, frame_time_ns, pred (M, 3) N, true (M, 3) N, and for a model with a band
band (M, 3) N, its half-width, and spread (M, 3) N, its signal), validation.npz (the same of the
validation frames, which the band was calibrated on) and metrics.json, written last (with the validation
split's pooled metrics under "val", the reference a test orientation's error is compared with, and the
band's coverage under "band", and the test frames whose input is unlike training's under "unfamiliar")."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from vfmodels.evaluation.band import distance_scale, unfamiliar_metrics
from vfmodels.experiment.variants import Variant
from vfmodels.reports.tables import run_metrics


def run_folder(out: Path, variant: Variant, seed: int) -> Path:
    return out / "runs" / variant.name / f"seed{seed}"


def write_run(run_dir: Path, predictions: dict[str, np.ndarray], summary: dict,
              validation: dict[str, np.ndarray] | None = None) -> dict:
    """predictions.npz, then metrics.json (written last: the marker of a finished run); `validation`:
    the same per-frame arrays on the validation split, summarised as "val"."""
    np.savez_compressed(run_dir / "predictions.npz", **predictions)
    metrics = run_metrics(predictions)
    groups = {str(k): v for k, v in metrics["groups"].items()}
    summary = {**summary, "test_frames": int(len(predictions["true"])), "pooled": metrics["pooled"],
               "mean": metrics["mean"], "std": metrics["std"], "groups": groups}
    if "band" in metrics:
        summary["band"] = {"pooled": metrics["band"]["pooled"],
                           "groups": {str(k): v for k, v in metrics["band"]["groups"].items()}}
    if validation is not None:
        np.savez_compressed(run_dir / "validation.npz", **validation)
        summary["val"] = run_metrics(validation)["pooled"]
        limit = distance_scale(validation.get("distance"))[1]
        if limit is not None and "distance" in predictions:
            known = np.isfinite(predictions["true"]).all(axis=1)
            summary["unfamiliar"] = unfamiliar_metrics(predictions["pred"][known], predictions["true"][known],
                                                       predictions["distance"][known], limit)
    tmp = run_dir / "metrics.json.partial"
    tmp.write_text(json.dumps(summary, indent=2))
    tmp.replace(run_dir / "metrics.json")
    return summary
