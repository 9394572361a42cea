"""How a tissue hangs against the tissues a model was trained on: its lean under gravity.

A tissue clamped at one end hangs under its own weight: the straight axis through it (the object frame's Z,
from the clamped end to the free one) leans below the clamp's axis, and a softer tissue leans more (on the
simulator's colon, log droop = -0.72 log modulus + 2.03 log length + ..., R² 0.91). The error of a force
model on a tissue it never saw is mostly a gain its stiffness sets (docs/results.md, "The tissues trained
on"), so the lean looked like a free stiffness cue. Measured (docs/results.md, "The droop and the lean";
`bench/study_droop_gain.py`): on the colon seeds where `MARGIN_DEG` was set, test views whose tissue hung
outside the training tissues' range erred 1.8x as much as the others; on 6 fresh seeds the 2 of 20 views so
named did not err more, and the model's gain followed the lean on some seeds and against it on others. So
the lean is recorded and described (the derived metadata, `lean.md`, the force file's `tissue_lean`), not
used as a warning. On the `glove` preset's short, stiff finger the droop (1.0-1.5 deg) is under the lean's
own error and it carries nothing.

The lean is measured against the horizontal (gravity from the ECM pose), so it needs `up_known`; what
matters is the lean relative to the training recordings', so a clamp that is not level but the same for
every recording cancels out. A lab that changes the fixture between specimens changes the lean too.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from vfdata.recon.object_frame import ObjectFrame
from vfdata.recording import Recording
from vfdata.recording.derived import DerivedMeta, DerivedRecording
from vfdata.rig import rig_for

# Beyond the training tissues' range by more than this (deg) is worth a note: about the lean's own error
# (against the simulator's tissue axis: rms 1.3 deg, median 0.9 over the sweep's colon recordings).
MARGIN_DEG = 1.0
# Fewer training tissues than this give no range to judge by: one or two are one or two draws of the spread.
MIN_TRAINING = 3


def lean_deg(z_axis: np.ndarray, up: np.ndarray) -> float:
    """The angle (deg) of an object frame's Z (unit, clamped end -> free end) below the horizontal, `up`
    gravity-up in the same coordinates: positive where the free end hangs lower than the clamped one."""
    z = np.asarray(z_axis, dtype=np.float64)
    u = np.asarray(up, dtype=np.float64)
    sine = float(z @ u) / (np.linalg.norm(z) * np.linalg.norm(u))
    return float(-np.degrees(np.arcsin(np.clip(sine, -1.0, 1.0))))


def frame_lean(frame: ObjectFrame, up: np.ndarray | None) -> float | None:
    """An object frame's lean (deg, `lean_deg`) where gravity is known and the frame is the tissue's, else None."""
    return None if up is None or frame.kind != "tissue" else lean_deg(frame.z_axis, up)


def beyond_range(lean: float, training: list[float], margin: float = MARGIN_DEG) -> float:
    """How far (deg) `lean` lies outside the range of the `training` leans, less `margin`: 0 within;
    negative for a tissue hanging higher (stiffer), positive lower (softer)."""
    low, high = min(training), max(training)
    if lean < low - margin:
        return lean - low
    if lean > high + margin:
        return lean - high
    return 0.0


def lean_report(leans: Mapping[str, tuple[str, float | None]], doubtful: set[str] = frozenset(),
                margin: float = MARGIN_DEG) -> dict:
    """From id -> (split, lean deg or None) of a manifest's recordings: the training range and, per validation
    or test recording, its lean and how far beyond. Recordings judged `doubtful` (`vfdata.confidence`) count
    nowhere: their object frame, so their lean, may be wrong, and the doubt is said already."""
    kept = {rid: (split, lean) for rid, (split, lean) in leans.items()
            if rid not in doubtful and lean is not None and math.isfinite(lean)}
    train = [lean for split, lean in kept.values() if split == "train"]
    report = {"training_deg": None, "training_recordings": len(train), "margin_deg": margin, "recordings": []}
    if len(train) < MIN_TRAINING:
        return report
    report["training_deg"] = [round(min(train), 2), round(max(train), 2)]
    report["recordings"] = [{"id": rid, "split": split, "lean_deg": round(lean, 2),
                             "beyond_deg": round(beyond_range(lean, train, margin), 2)}
                            for rid, (split, lean) in kept.items() if split != "train"]
    return report


def unlike_training(lean: float, training_deg: tuple[float, float] | list[float], margin: float = MARGIN_DEG
                    ) -> str | None:
    """The words for a tissue that hangs at `lean` (deg) outside the training tissues' (low, high) range by more
    than `margin`; None within it. A description, not a warning: it did not predict the error on fresh seeds."""
    low, high = training_deg
    if not beyond_range(lean, [low, high], margin):
        return None
    return f"hangs {level(lean)}, outside the training tissues' {low:.1f} to {high:.1f} deg below level"


def level(lean: float) -> str:
    """'4.2 deg below level', '1.3 deg above level'."""
    return f"{abs(lean):.1f} deg {'below' if lean >= 0 else 'above'} level"


def lean_metadata(lean: float | None, training_deg: list[float] | None) -> tuple[str | None, dict[str, str]]:
    """What a force file records of its tissue's lean against its model's training tissues (`vfdata predict`,
    `predict --stream`, `live --record`, `train.py predict`): the words when it hangs outside their range (None
    otherwise, or when either is unknown), and the `tissue_lean` metadata (JSON: lean_deg, training_deg,
    unlike_training)."""
    note = unlike_training(lean, training_deg) if lean is not None and training_deg is not None else None
    return note, {"tissue_lean": json.dumps({"lean_deg": None if lean is None else round(lean, 2),
                                             "training_deg": training_deg, "unlike_training": note})}


def lean_warnings(report: dict) -> list[str]:
    """One line per validation or test recording whose tissue hangs outside the training tissues' range."""
    if not report["training_deg"]:
        return []
    lines = []
    for row in report["recordings"]:
        words = unlike_training(row["lean_deg"], report["training_deg"], report["margin_deg"])
        if words:
            lines.append(f"{row['id']} ({row['split']}) {words}")
    return lines


def lean_markdown(report: dict) -> str:
    """`lean.md`: the training range, each validation and test recording's lean, the warnings."""
    low, high = report["training_deg"]
    lines = ["# How the tissues hang", "",
             f"Each recording's lean: the object frame's Z below the horizontal (deg; gravity from the ECM pose). "
             f"A softer tissue hangs lower. The {report['training_recordings']} training recordings not doubtful hang "
             f"{low:.1f}-{high:.1f} deg; those outside that range by more than {report['margin_deg']} deg are listed "
             "below. A description of the specimens, not a warning: on fresh simulated seeds it did not predict "
             "which test recordings erred more (docs/results.md, \"The droop and the lean\").", "",
             "| recording | split | lean (deg) | beyond training (deg) |", "| --- | --- | ---: | ---: |"]
    lines += [f"| {r['id']} | {r['split']} | {r['lean_deg']:.1f} | {r['beyond_deg']:+.1f} |" if r["beyond_deg"] else
              f"| {r['id']} | {r['split']} | {r['lean_deg']:.1f} | |" for r in report["recordings"]]
    notes = lean_warnings(report)
    return "\n".join(lines) + "\n" + ("\n" + "\n".join(f"- {n}" for n in notes) + "\n" if notes else "")


def read_lean(derived: Path, raw: Path) -> float | None:
    """A processed recording's lean (deg), from its derived file (`recording_lean`)."""
    with DerivedRecording.open(derived) as d:
        meta, frame = d.meta, d.object_frame
    return recording_lean(meta, frame, raw)


def recording_lean(meta: DerivedMeta, frame: ObjectFrame | None, raw: Path) -> float | None:
    """A processed recording's lean (deg) from its derived metadata: as `vfdata process` wrote it, or, in files
    from before it did, from their object frame and the raw recording's gravity (`raw`, its MCAP). None where
    gravity is unknown or the frame is not the tissue's."""
    if meta.tissue_lean_deg is not None:
        return float(meta.tissue_lean_deg)
    if not meta.up_known or meta.object_frame_kind != "tissue" or frame is None:
        return None
    with Recording.open(raw) as rec:
        return frame_lean(frame, rig_for(rec, raw).up)
