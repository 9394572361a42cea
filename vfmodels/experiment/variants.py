"""The rows of the force tables: each variant is a training config, the tracker whose tracks it
reads, and the table it belongs to. Plain data (no torch), so the command line can list them."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Variant:
    """One row of the force tables (I: the proposed model against the image baselines; II: ablations)."""

    name: str
    label: str
    config: str  # relative to configs/
    tracker: str = "geometry"
    table: str = "II"


# The project's own pipeline, the default for users: the paper's network on deformation tokens with the
# tube's mirror symmetry (docs/results.md), and its camera-frame twin for the object-frame claim.
VISIONFORCE_VARIANTS: dict[str, Variant] = {v.name: v for v in (
    Variant("visionforce", "VisionForce (displacement tokens, mirror symmetry)", "visionforce.yaml", table="I+II"),
    Variant("visionforce_camera_frame", "VisionForce, camera frame", "visionforce_camera_frame.yaml"),
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

# Upper bounds that read the simulator's ground-truth tracks (tracker `groundtruth`: the true material
# positions of the same 256 points the geometry tracker starts from, visibility from the estimated
# mask, object frame estimated as for the proposed model). They separate the tracker's errors from the
# representation's. Only on request: they need `ground_truth/` beside every raw folder.
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

ALL_VARIANTS: dict[str, Variant] = {**VISIONFORCE_VARIANTS, **PAPER_VARIANTS, **SIMULATOR_VARIANTS, **EXTRA_VARIANTS}
DEFAULT_VARIANTS: tuple[str, ...] = (*VISIONFORCE_VARIANTS, *PAPER_VARIANTS)

# Derived file name per tracker (a manifest's `processed:` points the datasets at it).
TRACKER_SUFFIX = {"geometry": ".processed.mcap", "klt": ".klt.mcap", "geometry+": ".geometry_plus.mcap",
                  "groundtruth": ".gt.mcap"}


def derived_name(recording_id: str, tracker: str) -> str:
    return recording_id + TRACKER_SUFFIX.get(tracker, f".{tracker}.mcap")
