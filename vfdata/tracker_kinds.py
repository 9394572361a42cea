"""What each point tracker is: the facts the commands, the device policy, RGB-D processing and the
reports need, in one table (light: no torch or OpenCV, so `vfdata --help` stays fast). The trackers
themselves are built by `vfdata.tracking.registry.make_tracker`, which has one maker per entry here."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class TrackerKind:
    name: str
    label: str  # in reports and tables
    help: str  # a few words for `--tracker`
    gpu: bool = False  # has a GPU path (`--device cuda` puts it there; others stay on the CPU)
    # Follows the image texture: on an RGB-D recording the image is its depth drawn as grey, whose
    # brightness a press changes, so processing warns.
    reads_images: bool = False
    rgbd_options: dict = field(default_factory=dict)  # defaults on RGB-D recordings (rig.RgbdRig.stage_options)


# An organ on a board stays in place and only dents: without a weak anchor to the reference positions the
# geometry trackers' points slid 3 mm along the surface over 200 frames at rest on the Gao et al. recording
# (0.2 mm with it, and the tracked press follows Fz more closely).
_RGBD_ANCHOR = {"lambda_anchor": 1.0}

TRACKER_KINDS: dict[str, TrackerKind] = {k.name: k for k in (
    TrackerKind("geometry", "Geometry-constrained (proposed)", "the paper's SIREN field under Chamfer + LLR (default)",
                gpu=True, rgbd_options=_RGBD_ANCHOR),
    TrackerKind("geometry+", "Geometry+ (with image flow)", "geometry that also follows the image texture",
                gpu=True, reads_images=True, rgbd_options=_RGBD_ANCHOR),
    TrackerKind("klt", "KLT (CoTracker stand-in)", "Lucas-Kanade in the left image, lifted with the depth",
                reads_images=True),
    TrackerKind("cotracker", "CoTracker", "CoTracker over the whole clip (needs its weights)", reads_images=True),
    TrackerKind("groundtruth", "Ground truth", "the simulator's true material points"),
    TrackerKind("static", "Static (lower bound)", "the reference points standing still"),
)}
NO_TRACKER = "none"  # processing without tracks

TRACKER_HELP = "point tracker: " + "; ".join(f"{k.name}: {k.help}" for k in TRACKER_KINDS.values()) + \
    f"; {NO_TRACKER}: no tracks"
GPU_TRACKERS: tuple[str, ...] = tuple(k.name for k in TRACKER_KINDS.values() if k.gpu)
IMAGE_TRACKERS: tuple[str, ...] = tuple(k.name for k in TRACKER_KINDS.values() if k.reads_images)


def tracker_label(name: str) -> str:
    """The tracker's label in reports (its name when it is not one of ours)."""
    kind = TRACKER_KINDS.get(name)
    return kind.label if kind is not None else name
