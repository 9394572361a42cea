"""Presets: which recordings a dataset has (ids, orientation, split, length) and the ranges from which
each recording's tissue, material, camera and motion are drawn.

`glove` follows the paper's rubber-glove finger phantom study (about 16,300 frames, 7:2:1
train/val/test, test at 90 and 180 degrees); `colon` its ex vivo porcine colon study (about 5,300
frames, 7:1.5:1.5); `mini` is a few hundred frames per recording for tests and the Quickstart.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

from vfdata.errors import VisionForceError
from vfdata.sim.texture import Palette

FPS = 30.0


@dataclass(frozen=True)
class TissueKind:
    """Ranges (lo, hi) of a study's tissue and how it is filmed and handled."""

    study: str
    description: str
    length_mm: tuple[float, float]
    diameter_mm: tuple[float, float]
    tip_ratio: tuple[float, float]          # free-end radius / clamped-end radius
    n_rings: int
    n_around: int
    axial_stiffness_n_mm: tuple[float, float]  # nominal pull stiffness E * wall * 2 pi r / L; sets E
    wall_mm: tuple[float, float]
    density_kg_m3: float
    stiffening: tuple[float, float]
    compression_ratio: float
    kelvin_voigt_s: tuple[float, float]
    maxwell_ratio: tuple[float, float]
    maxwell_tau_s: tuple[float, float]
    kind_factors: tuple[float, ...]
    grasp_fraction: tuple[float, float]     # grasp point position along the tube
    # Reach of the grasp point as fractions of the tube length (object frame X up, Y, Z along).
    reach_lo: tuple[float, float, float]
    reach_hi: tuple[float, float, float]
    camera_distance_mm: tuple[float, float]
    palette: Palette
    dense_s: int
    dense_theta: int


GLOVE = TissueKind(
    study="glove",
    description="finger of a latex glove filled with soft silicone, clamped at its base",
    length_mm=(56.0, 64.0),
    diameter_mm=(16.0, 20.0),
    tip_ratio=(0.8, 0.9),
    n_rings=16,
    n_around=12,
    axial_stiffness_n_mm=(0.24, 0.30),
    wall_mm=(1.4, 1.6),
    density_kg_m3=1050.0,
    stiffening=(3.0, 5.0),
    compression_ratio=0.3,
    kelvin_voigt_s=(0.03, 0.06),
    maxwell_ratio=(0.25, 0.4),
    maxwell_tau_s=(0.8, 2.0),
    kind_factors=(1.0, 1.0, 0.5, 3.0, 0.5, 2.0),
    grasp_fraction=(0.74, 0.82),
    reach_lo=(-0.15, -0.42, -0.05),
    reach_hi=(0.45, 0.42, 0.1),
    camera_distance_mm=(84.0, 96.0),
    palette=Palette(light=(0.80, 0.58, 0.46), dark=(0.66, 0.40, 0.32), vessel=(0.42, 0.07, 0.09),
                    blotch=(0.75, 0.36, 0.34), vessel_count=5, gloss=0.55, shininess=70.0, grain=0.22),
    dense_s=34,
    dense_theta=28,
)

COLON = TissueKind(
    study="colon",
    description="ex vivo porcine colon segment, closed at the free end, clamped at its wide end",
    length_mm=(100.0, 140.0),
    diameter_mm=(25.0, 35.0),
    tip_ratio=(0.65, 0.8),
    n_rings=20,
    n_around=14,
    axial_stiffness_n_mm=(0.17, 0.21),  # Fz ranged 15-30 N per recording at 0.21-0.26
    wall_mm=(2.0, 3.0),
    density_kg_m3=1040.0,
    stiffening=(3.0, 6.0),
    compression_ratio=0.15,
    kelvin_voigt_s=(0.06, 0.12),
    maxwell_ratio=(0.4, 0.7),
    maxwell_tau_s=(1.0, 3.0),
    kind_factors=(1.0, 1.0, 0.6, 4.5, 0.5, 4.0),
    grasp_fraction=(0.72, 0.82),
    reach_lo=(-0.1, -0.34, -0.03),
    reach_hi=(0.36, 0.34, 0.04),
    camera_distance_mm=(132.0, 145.0),
    palette=Palette(light=(0.74, 0.36, 0.34), dark=(0.46, 0.10, 0.12), vessel=(0.30, 0.02, 0.05),
                    blotch=(0.78, 0.52, 0.42), vessel_count=14, gloss=0.8, shininess=80.0, grain=0.16),
    dense_s=44,
    dense_theta=32,
)

BED_PALETTE = Palette(light=(0.78, 0.40, 0.44), dark=(0.30, 0.02, 0.06), vessel=(0.24, 0.01, 0.03),
                      blotch=(0.90, 0.72, 0.70), vessel_count=16, gloss=0.7, shininess=60.0, grain=0.12)


@dataclass(frozen=True)
class RecordingPlan:
    id: str
    index: int
    orientation_deg: float
    split: str
    frames: int
    tissue: TissueKind


@dataclass(frozen=True)
class Preset:
    name: str
    tissue: TissueKind
    recordings: tuple[RecordingPlan, ...]
    width: int = 640
    height: int = 512

    @property
    def total_frames(self) -> int:
        return sum(r.frames for r in self.recordings)


def _plan(name: str, tissue: TissueKind, groups: list[tuple[str, float, list[int]]]) -> Preset:
    recs = []
    for split, orientation, lengths in groups:
        for frames in lengths:
            k = len(recs)
            recs.append(RecordingPlan(f"{name}_{k:03d}", k, orientation, split, frames, tissue))
    return Preset(name, tissue, tuple(recs))


PRESETS: dict[str, Preset] = {
    "mini": _plan("mini", GLOVE, [("train", 0.0, [240]), ("val", 0.0, [150]), ("test", 90.0, [150])]),
    # 11,400 + 3,260 + 1,632 = 16,292 frames (7 : 2 : 1).
    "glove": _plan("glove", GLOVE, [("train", 0.0, [950] * 12), ("val", 0.0, [815] * 4),
                                     ("test", 90.0, [408] * 2), ("test", 180.0, [408] * 2)]),
    # 3,710 + 795 + 796 = 5,301 frames (7 : 1.5 : 1.5).
    "colon": _plan("colon", COLON, [("train", 0.0, [742] * 5), ("val", 0.0, [795]),
                                     ("test", 90.0, [398]), ("test", 180.0, [398])]),
}


def get_preset(name: str, test_orientations: Sequence[float] | None = None,
               split_recordings: Mapping[str, int] | None = None) -> Preset:
    """The preset `name`, with its test recordings turned to `test_orientations` if given
    (`with_test_orientations`), then with as many recordings per split as `split_recordings` says
    ({"train": 10, "val": 3}; `with_split_recordings`, new ones in that order)."""
    if name not in PRESETS:
        raise VisionForceError(f"unknown preset '{name}' (choose from {', '.join(PRESETS)})")
    preset = PRESETS[name]
    if test_orientations is not None:
        preset = with_test_orientations(preset, test_orientations)
    for split, count in counted_splits(split_recordings):
        preset = with_split_recordings(preset, split, count)
    return preset


def counted_splits(split_recordings: Mapping[str, int | None] | None) -> list[tuple[str, int]]:
    """(split, count) of the splits whose count is given, train before val: the order new recordings
    are added in (their indices, so their draws, depend on it)."""
    given = split_recordings or {}
    return [(split, given[split]) for split in ("train", "val") if given.get(split) is not None]


def with_test_orientations(preset: Preset, orientations: Sequence[float]) -> Preset:
    """The preset with its test recordings spread over `orientations` (degrees about the vertical),
    in order and as evenly as possible: of n test recordings and k orientations, recording j gets
    orientation floor(j k / n) (the preset's own 90, 180 over four recordings: 90, 90, 180, 180).
    Their ids and lengths stay; with more orientations than test recordings, test recordings of the
    same length are added after the others (new ids, new draws), one per orientation. As for the
    preset's own, the camera's viewpoint and the tissue's place in the image follow from the
    orientation and the recording's draws."""
    orientations = [float(a) for a in orientations]
    tests = [r for r in preset.recordings if r.split == "test"]
    if not orientations:
        raise VisionForceError("test orientations: give at least one angle in degrees")
    bad = [a for a in orientations if not math.isfinite(a)]
    if bad:
        raise VisionForceError(f"test orientations: {bad[0]} is not an angle in degrees")
    if not tests:
        raise VisionForceError(f"test orientations: preset '{preset.name}' has no test recordings")
    if len(orientations) > len(tests):
        start = len(preset.recordings)
        extra = tuple(replace(tests[-1], index=start + k, id=f"{preset.name}_{start + k:03d}")
                      for k in range(len(orientations) - len(tests)))
        preset = replace(preset, recordings=preset.recordings + extra)
        tests = list(tests) + list(extra)
    turned = {r.index: orientations[j * len(orientations) // len(tests)] for j, r in enumerate(tests)}
    recordings = tuple(replace(r, orientation_deg=turned[r.index]) if r.index in turned else r
                       for r in preset.recordings)
    return replace(preset, recordings=recordings)


def with_train_recordings(preset: Preset, count: int) -> Preset:
    """The preset with `count` training recordings (`with_split_recordings`)."""
    return with_split_recordings(preset, "train", count)


def with_split_recordings(preset: Preset, split: str, count: int) -> Preset:
    """The preset with `count` recordings in `split` (train or val): its first `count` ones, or all of
    them and new ones of the same length after every other recording (new ids, new draws). Each recording
    draws its tissue, material, motion and camera from the seed and its index, so the other recordings
    stay as they were: the same test recordings, trained (or validated) on fewer or more tissues
    (docs/results.md: on fresh seeds the error on an unseen tissue is mostly a gain that its mechanics
    set, and it falls with the number of tissues trained on)."""
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise VisionForceError(f"{split} recordings: {count!r} is not a number of recordings >= 1")
    own = [r for r in preset.recordings if r.split == split]
    if not own:
        raise VisionForceError(f"{split} recordings: preset '{preset.name}' has none")
    dropped = {r.index for r in own[count:]}
    start = len(preset.recordings)
    extra = tuple(replace(own[-1], index=start + k, id=f"{preset.name}_{start + k:03d}")
                  for k in range(count - len(own)))
    return replace(preset, recordings=tuple(r for r in preset.recordings if r.index not in dropped) + extra)
