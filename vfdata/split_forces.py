"""Can a manifest's splits test what they claim? The forces of each split, before any training.

Two things in a split's labels decide what a model of the video can learn, whatever the model:

- **Force beyond training.** A regression rarely extrapolates: test frames whose force lies beyond
  the training range (per component, by more than a tenth of it) are under-predicted by every model
  we have tried (Gao et al. 2018: the test stretch's -105 N press against training's -66 N;
  docs/results.md).
- **Coupled components.** Components that always move together in training cannot be told apart:
  the model learns one from the other's motion, and a test where they come apart finds it out (on the
  same recording training couples Fz to Fx at -0.52, the test stretch at 0.08).

`summarise` is pure (forces per split -> figures), `manifest_forces` reads the labels (the force at
each frame of each entry's frame range, N), `split_warnings` words what a user should know, and
`write_split_report` leaves `splits.json` and `splits.md` beside an experiment's results.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from vfdata.manifest import Manifest
from vfdata.recording import Recording

COMPONENTS = ("fx", "fy", "fz")
LABELS = {"fx": "Fx", "fy": "Fy", "fz": "Fz"}
# A frame is beyond training when a component lies outside training's range by more than this share of
# that range: a component that stays near zero in training (0.2 N of sensor noise) should not make every
# small excursion of a test "unseen".
BEYOND_MARGIN = 0.1
BEYOND_WARN = 0.05  # share of a split's frames beyond training worth a warning
COUPLING_WARN = 0.95  # |correlation| between two components in training worth a warning (the simulator's
# tube couples Fx and Fz at 0.8-0.9 in every split; Gao et al.'s pulls Fx and Fy at 0.98 in training only)
PAIRS = (("fx", "fy"), ("fx", "fz"), ("fy", "fz"))


def manifest_forces(manifest: Manifest) -> dict[str, np.ndarray]:
    """Split -> (T, 3) the force (N) at every frame of its entries (within each entry's `frames`
    range), frames without a force sample left out."""
    parts: dict[str, list[np.ndarray]] = {}
    for entry in manifest.entries:
        with Recording.open(entry.mcap) as rec:
            times = rec.frame_times_ns
            if entry.frames is not None:
                times = times[slice(*entry.frames)]
            force = rec.force_at(times)[:, :3]
        parts.setdefault(entry.split, []).append(force[np.isfinite(force).all(axis=1)])
    return {split: np.concatenate(chunks) for split, chunks in parts.items()}


def component_coupling(force_n: np.ndarray) -> dict[str, float | None]:
    """Correlations between the force components (T, 3): `fx_fy`, `fx_fz`, `fy_fz` (None for fewer
    than three frames or a component that does not vary)."""
    if len(force_n) < 3:
        return {f"{a}_{b}": None for a, b in PAIRS}
    spread = force_n.std(axis=0) > 1e-9
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.corrcoef(force_n.T)
    index = {name: i for i, name in enumerate(COMPONENTS)}
    return {f"{a}_{b}": float(c[index[a], index[b]]) if spread[index[a]] and spread[index[b]] else None
            for a, b in PAIRS}


def outside_training(force_n: np.ndarray, train_force_n: np.ndarray,
                     margin: float = BEYOND_MARGIN) -> tuple[np.ndarray, np.ndarray]:
    """(below, above), each (T, 3) bool: which components of each frame (T, 3) lie below / above the
    training forces' range (per component) by more than `margin` of that range (0: any value outside)."""
    train = np.asarray(train_force_n, dtype=np.float64)
    low, high = train.min(axis=0), train.max(axis=0)
    slack = margin * (high - low)
    force = np.asarray(force_n, dtype=np.float64)
    return force < low - slack, force > high + slack


def beyond_training(force_n: np.ndarray, train_force_n: np.ndarray, margin: float = BEYOND_MARGIN) -> np.ndarray:
    """(T, 3) bool: the components of each frame outside the training range (`outside_training`)."""
    below, above = outside_training(force_n, train_force_n, margin)
    return below | above


def training_range(force_n: np.ndarray, mirror: bool = False, rotate: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) (3,) N: the range of the training forces (M, 3) per component as training saw them:
    with the mirror across XZ Fy is seen with both signs, with turns about Z Fx and Fy take every
    direction up to the largest horizontal force."""
    force = np.asarray(force_n, dtype=np.float64).reshape(-1, 3)
    force = force[np.isfinite(force).all(axis=1)]
    low, high = force.min(axis=0), force.max(axis=0)
    if rotate:
        reach = float(np.hypot(force[:, 0], force[:, 1]).max())
        low[:2], high[:2] = -reach, reach
    elif mirror:
        reach = float(np.abs(force[:, 1]).max())
        low[1], high[1] = -reach, reach
    return low, high


def summarise(forces: dict[str, np.ndarray]) -> dict[str, dict]:
    """Per split: frames, each component's min and max (N), how the components correlate, and (for
    every split but train) the share of frames with a component beyond training's range (by more than
    `BEYOND_MARGIN` of it), per component and any."""
    train = forces.get("train")
    out = {}
    for split, force in forces.items():
        force = np.asarray(force, dtype=np.float64).reshape(-1, 3)
        row: dict = {"frames": len(force),
                     "min_n": force.min(axis=0).round(3).tolist() if len(force) else None,
                     "max_n": force.max(axis=0).round(3).tolist() if len(force) else None,
                     "coupling": component_coupling(force)}
        if split != "train" and train is not None and len(train) and len(force):
            beyond = beyond_training(force, train)
            row["beyond_training"] = float(beyond.any(axis=1).mean())
            row["beyond_training_per_component"] = dict(zip(COMPONENTS, beyond.mean(axis=0).round(4).tolist(),
                                                            strict=True))
        out[split] = row
    return out


def split_warnings(summary: dict[str, dict]) -> list[str]:
    """One line per thing a user should know before reading the test figures."""
    lines = []
    train = summary.get("train")
    for split, row in summary.items():
        share = row.get("beyond_training")
        if share is not None and share > BEYOND_WARN:
            trained = np.array([train["min_n"], train["max_n"]])
            below = outside_training(np.array([row["min_n"]]), trained)[0][0]
            above = outside_training(np.array([row["max_n"]]), trained)[1][0]
            beyond = []
            for k, c in enumerate(COMPONENTS):
                if below[k]:
                    beyond.append(f"{LABELS[c]} down to {row['min_n'][k]:.1f} N (training {train['min_n'][k]:.1f})")
                if above[k]:
                    beyond.append(f"{LABELS[c]} up to {row['max_n'][k]:.1f} N (training {train['max_n'][k]:.1f})")
            lines.append(f"{split}: {share:.0%} of its {row['frames']} frames have force beyond the training range by "
                         f"more than a tenth of it ({', '.join(beyond)}): expect them under-predicted")
    if train is not None:
        coupled = [f"{LABELS[a]}-{LABELS[b]} {v:+.2f}" for (a, b), v in
                   zip(PAIRS, train["coupling"].values(), strict=True) if v is not None and abs(v) >= COUPLING_WARN]
        if coupled:
            lines.append(f"train: components move together ({', '.join(coupled)}): a model cannot tell them apart, "
                         "and a test where they come apart will show it")
    return lines


def write_split_report(out: Path, summary: dict[str, dict]) -> list[Path]:
    """`splits.json` (the summary) and `splits.md` (a table and the warnings) in OUT."""
    out.mkdir(parents=True, exist_ok=True)
    lines = ["| split | frames | Fx (N) | Fy (N) | Fz (N) | beyond training | Fx-Fy / Fx-Fz / Fy-Fz |",
             "| --- | ---: | --- | --- | --- | ---: | --- |"]
    for split, row in summary.items():
        ranges = [f"{lo:.1f} to {hi:.1f}" for lo, hi in zip(row["min_n"], row["max_n"], strict=True)] \
            if row["min_n"] is not None else ["", "", ""]
        beyond = row.get("beyond_training")
        coupling = " / ".join("n/a" if v is None else f"{v:+.2f}" for v in row["coupling"].values())
        lines.append(f"| {split} | {row['frames']} | " + " | ".join(ranges)
                     + f" | {'' if beyond is None else f'{beyond:.0%}'} | {coupling} |")
    notes = split_warnings(summary)
    text = "**Forces of the splits** (N; correlations between components)\n\n" + "\n".join(lines) + "\n"
    if notes:
        text += "\n" + "\n".join(f"- {note}" for note in notes) + "\n"
    paths = [out / "splits.json", out / "splits.md"]
    paths[0].write_text(json.dumps(summary, indent=1))
    paths[1].write_text(text)
    return paths
