"""The rows of the force tables: each variant is a training config (with overrides), the processed
files it reads, and the table it belongs to. Plain data (no torch), so the command line can list them."""

from __future__ import annotations

from dataclasses import dataclass, replace


@dataclass(frozen=True)
class Processing:
    """How a recording's derived file for some variants is made, and its name (`<id><suffix>`)."""

    suffix: str
    tracker: str = "geometry"
    depth: str | None = None  # None: the experiment's --depth
    segment: str | None = None  # None: the experiment's --segment


PROCESSINGS: dict[str, Processing] = {
    "geometry": Processing(".processed.mcap"),
    "klt": Processing(".klt.mcap", "klt"),
    "geometry+": Processing(".geometry_plus.mcap", "geometry+"),
    "groundtruth": Processing(".gt.mcap", "groundtruth"),
    # the simulator's true depth and mask, our object frame and geometry tracker (a ladder rung)
    "truedepth": Processing(".truedepth.mcap", "geometry", depth="recorded", segment="recorded"),
}


@dataclass(frozen=True)
class Variant:
    """One row of the force tables (I: the models against the image baselines; II: ablations)."""

    name: str
    label: str
    config: str  # relative to configs/
    tracker: str = "geometry"  # a key of PROCESSINGS: which derived files it reads
    table: str = "II"
    overrides: tuple[str, ...] = ()  # extra LightningCLI arguments, e.g. "--data.spec.source=ground_truth"
    kind: str = "network"  # "network" (LightningCLI) or "ridge" (vfmodels.networks.ridge on the config's tokens)


# The project's own pipeline, the default for users: the paper's network on deformation tokens with the
# tube's mirror symmetry (docs/results.md), its camera-frame twin, and the fast ridge model on its tokens.
# They read KLT tracks: with tokens that carry each point's place along Z, tracks that do not slide along
# the surface halve the error on glove (1.21 -> 0.56 N, seed 0; docs/results.md, "VisionForce").
# On an RGB-D recording the image trackers see the depth drawn as grey (the colour crop is not
# registered to it): a press changes the very brightness KLT follows, and its tracks leave the tissue
# (Gao et al. 2018: test R² -0.83 on KLT tracks, 0.32 on geometry tracks; docs/results.md). There the
# project's pipeline reads the geometry tracker's, which needs only the depth.
VISIONFORCE_TRACKER = "klt"
VISIONFORCE_DEPTH_ONLY_TRACKER = "geometry"
VISIONFORCE_VARIANTS: dict[str, Variant] = {v.name: v for v in (
    Variant("visionforce", "VisionForce (deformation tokens, tube symmetries)", "visionforce.yaml",
            tracker=VISIONFORCE_TRACKER, table="I+II"),
    Variant("visionforce_camera_frame", "VisionForce, camera frame", "visionforce_camera_frame.yaml",
            tracker=VISIONFORCE_TRACKER),
    Variant("ridge", "Ridge on VisionForce's tokens (pooled moments, seconds to train)", "visionforce.yaml",
            tracker=VISIONFORCE_TRACKER, kind="ridge"),
)}

# The paper's feature ablation for the project's pipeline, only by name: displacement alone, velocity alone.
VISIONFORCE_ABLATIONS: dict[str, Variant] = {v.name: v for v in (
    Variant("visionforce_displacement_only", "VisionForce, displacement only", "visionforce.yaml",
            tracker=VISIONFORCE_TRACKER,
            overrides=("--data.spec.features=disp", "--data.spec.radius=mm", "--model.model.init_args.in_features=3")),
    Variant("visionforce_velocity_only", "VisionForce, velocity only", "visionforce.yaml",
            tracker=VISIONFORCE_TRACKER,
            overrides=("--data.spec.features=vel", "--data.spec.radius=mm", "--model.model.init_args.in_features=3")),
    Variant("visionforce_relaxation", "VisionForce, with the relaxation", "visionforce.yaml",
            tracker=VISIONFORCE_TRACKER,
            overrides=("--data.spec.features=polar_z_disp_relax_vel", "--model.model.init_args.in_features=15")),
    Variant("ridge_relaxation", "Ridge, with the relaxation", "visionforce.yaml", tracker=VISIONFORCE_TRACKER,
            kind="ridge", overrides=("--data.spec.features=polar_z_disp_relax_vel",)),
)}

# The paper's grid: `proposed` is the paper's method, faithfully; the ablations and baselines around it.
PAPER_VARIANTS: dict[str, Variant] = {v.name: v for v in (
    Variant("proposed", "Proposed (object frame, geometry tracking)", "proposed.yaml", table="I+II"),
    Variant("camera_frame", "Camera frame", "ablation_camera_frame.yaml"),
    Variant("klt", "KLT tracking (CoTracker stand-in)", "proposed.yaml", tracker="klt"),
    Variant("point_cloud", "Point cloud", "ablation_point_cloud.yaml"),
    Variant("position_only", "Position only", "ablation_position_only.yaml"),
    Variant("velocity_only", "Velocity only", "ablation_velocity_only.yaml"),
    Variant("top_bottom", "Top/bottom 20%", "ablation_top_bottom.yaml"),
    Variant("rgb", "RGB only (3D ResNet-18)", "baseline_rgb.yaml", table="I"),
    Variant("depth_vit", "Masked depth + ViT-Small", "baseline_depth_vit.yaml", table="I"),
)}

# Upper bounds that read the simulator's ground-truth tracks (the true material positions of the same
# 256 points the geometry tracker starts from, visibility from the estimated mask, object frame
# estimated). Only on request: they need `ground_truth/` beside every raw folder.
SIMULATOR_VARIANTS: dict[str, Variant] = {v.name: v for v in (
    Variant("groundtruth", "Ground-truth tracks (simulator upper bound)", "proposed.yaml", tracker="groundtruth"),
    Variant("camera_frame_groundtruth", "Camera frame, ground-truth tracks", "ablation_camera_frame.yaml",
            tracker="groundtruth"),
)}

# Beyond the paper, only on request: every recording mirrored to the flank its first frame shows, and
# the proposed model on the tracks of `geometry+` (the geometry tracker that also follows the texture).
EXTRA_VARIANTS: dict[str, Variant] = {v.name: v for v in (
    Variant("canonical_side", "Proposed, mirrored to the seen flank (beyond the paper)",
            "proposed_canonical_side.yaml"),
    Variant("geometry_plus", "Proposed on geometry+ tracks (beyond the paper)", "proposed.yaml",
            tracker="geometry+"),
)}

# The attribution ladder (`vfdata experiment --ladder`, simulator only): the same model and split with
# each stage's output replaced by the simulator's truth in turn, from the top rung down to the real
# pipeline (the model's own variant).
LADDER_RUNGS: dict[str, tuple[str, tuple[str, ...], str]] = {
    # rung: (processing, overrides, label)
    "surface": ("geometry", ("--data.spec.source=ground_truth_surface",), "true points on the whole surface"),
    "visible": ("geometry", ("--data.spec.source=ground_truth",), "true points visible in frame 0, true frame"),
    "truetracks": ("groundtruth", (), "true tracks, our depth, mask and object frame"),
    "truedepth": ("truedepth", (), "true depth and mask, our object frame and tracker"),
}
LADDER_MODELS = ("visionforce", "proposed", "ridge")


def _ladder() -> dict[str, Variant]:
    base = {**VISIONFORCE_VARIANTS, **PAPER_VARIANTS}
    variants = {}
    for model in LADDER_MODELS:
        v = base[model]
        for rung, (processing, overrides, label) in LADDER_RUNGS.items():
            variants[f"{model}@{rung}"] = Variant(f"{model}@{rung}", f"{v.label.split(' (')[0]}: {label}", v.config,
                                                  processing, "ladder", overrides, v.kind)
    return variants


LADDER_VARIANTS: dict[str, Variant] = _ladder()

# The project's pipeline on the other trackers' tracks, only by name: the paper's geometry tracker (its
# tracks slide 3-4 mm along the surface) and geometry+ (it also follows the image texture).
TRACKER_VARIANTS: dict[str, Variant] = {
    f"{model}@{tracker}": Variant(f"{model}@{tracker}", f"{VISIONFORCE_VARIANTS[model].label.split(' (')[0]} on "
                                  f"{tracker} tracks", VISIONFORCE_VARIANTS[model].config, tracker, "II",
                                  kind=VISIONFORCE_VARIANTS[model].kind)
    for model in ("visionforce", "ridge") for tracker in ("geometry", "geometry+")
}

ALL_VARIANTS: dict[str, Variant] = {**VISIONFORCE_VARIANTS, **VISIONFORCE_ABLATIONS, **PAPER_VARIANTS,
                                    **SIMULATOR_VARIANTS, **EXTRA_VARIANTS, **LADDER_VARIANTS, **TRACKER_VARIANTS}
DEFAULT_VARIANTS: tuple[str, ...] = (*VISIONFORCE_VARIANTS, *PAPER_VARIANTS)
LADDER: tuple[str, ...] = (*LADDER_VARIANTS, *LADDER_MODELS)

# Derived file name per processing (a manifest's `processed:` points the datasets at it).
TRACKER_SUFFIX = {name: p.suffix for name, p in PROCESSINGS.items()}


def derived_name(recording_id: str, tracker: str) -> str:
    return recording_id + TRACKER_SUFFIX.get(tracker, f".{tracker}.mcap")


# An RGB-D recording is processed in the board frame of a flat organ (or the camera frame), never the
# tube's (vfdata.processing): the tube's mirror, turns and tilted axis are not symmetries there. Measured on
# Gao et al. 2018 with the turns kept: test R² 0.22 against 0.32 without (docs/results.md).
FLAT_TISSUE_OVERRIDES = ("--data.spec.mirror_augment=false", "--data.spec.rotate_augment=false",
                         "--data.spec.tilt_augment_deg=0", "--model.symmetry_turns=0")


def for_depth_only(variants: list[Variant]) -> list[Variant]:
    """The variants as they run on RGB-D recordings: the project's pipeline (and its camera-frame twin,
    ablations and ridge) on the depth-only tracker instead of KLT and without the tube's symmetries
    (`FLAT_TISSUE_OVERRIDES`, on every variant of a VisionForce config; a run's --train-arg still comes
    after them); a variant that names its tracker (the paper's `klt` ablation, `visionforce@geometry`)
    keeps it. The paper's configs have no symmetries to switch off."""
    own = {*VISIONFORCE_VARIANTS, *VISIONFORCE_ABLATIONS}
    flat = []
    for v in variants:
        if v.name in own:
            v = replace(v, tracker=VISIONFORCE_DEPTH_ONLY_TRACKER)
        if v.config.startswith("visionforce"):
            v = replace(v, overrides=(*FLAT_TISSUE_OVERRIDES, *v.overrides),
                        label=v.label.replace("tube symmetries", "flat tissue: no symmetries"))
        flat.append(v)
    return flat
