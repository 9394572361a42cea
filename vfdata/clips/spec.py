"""`ClipSpec`: how a recording becomes model input. One frozen dataclass, shared by the dataset, the
Lightning data module (where jsonargparse reads it as `--data.spec.<field>`), prediction and the
live estimator, and saved in every checkpoint, so a model always sees what it was trained on."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any, Literal, get_args

from vfdata.errors import VisionForceError

Input = Literal["tracks", "cloud", "rgb", "depth"]
Source = Literal["processed", "ground_truth", "ground_truth_surface"]
Frame = Literal["object", "camera"]
Features = Literal["pos_vel", "pos", "vel", "disp_vel", "disp", "ref_disp_vel", "polar_disp_vel", "polar_z_disp_vel",
                   "polar_z_disp_relax_vel"]
Subset = Literal["all", "top_bottom_20"]
Radius = Literal["mm", "tissue"]

FEATURE_CHANNELS = {"pos_vel": 6, "pos": 3, "vel": 3, "disp_vel": 6, "disp": 3, "ref_disp_vel": 9,
                    "polar_disp_vel": 9, "polar_z_disp_vel": 12, "polar_z_disp_relax_vel": 15}
# Features a tilt of the object frame can be applied to after the fact (`tokens.tilt_tokens`): 3-vectors
# that turn with it, or polar_z's place, which with its place along Z gives the point relative to the tip.
TILTABLE_FEATURES = ("polar_z_disp_vel", "polar_z_disp_relax_vel", "disp_vel", "disp", "vel", "ref_disp_vel",
                     "pos_vel", "pos")
INPUT_KEYS = {"tracks": "tokens", "cloud": "tokens", "rgb": "images", "depth": "depth"}


@dataclass(frozen=True)
class ClipSpec:
    """Clips of `clip_frames` consecutive frames, one starting every `stride` frames.

    Args:
        input: tracks (the tracked points, default), cloud (points drawn from the tissue cloud, no
            correspondences), rgb (the left image; the RGB baseline) or depth (the tissue-masked depth;
            the depth ViT baseline).
        source: processed (the derived MCAPs of `vfdata process`), ground_truth (the simulator's true
            material points among those visible on the first frame, valid where visible, in the true
            object frame) or ground_truth_surface (true points from the whole surface, all valid: what no
            camera sees). The two simulator sources are the top rungs of the attribution ladder.
        frame: object (the object-centred frame, default) or camera (the left camera frame).
        features: per-point channels, each a 3-vector: pos_vel (position mm + velocity mm/s, the
            paper's), pos, vel, disp_vel (displacement from the point's position on the recording's
            first frame, mm, + velocity: deformation, not where the point is) or ref_disp_vel (that
            first-frame position, the displacement and the velocity) or polar_disp_vel (where the point sits
            around the object's Z axis on its first frame as (cos th0, sin th0, r0 mm), th0 measured from X =
            up, then the displacement and the velocity: no position along Z, so no origin needed) or
            polar_z_disp_vel (the same with (0, 0, z0 - z_tip mm) after the polar place: the place along Z
            counted from the tissue's free end, which a view cutting the clamped end off does not move) or
            polar_z_disp_relax_vel (the same with the relaxation after the displacement: the displacement
            less its causal exponential average over `RELAX_TAU_S`, mm: how far a point sits from where it
            has been for the last seconds, which a viscoelastic tissue's force depends on; beyond the paper).
        radius: how the polar features give a point's distance from the Z axis, r0: mm, or tissue (r0 over the
            tissue's radius on the recording's first frame, the median r0 of its visible tracked points, so 1 on
            the surface; beyond the paper). A partial view from behind sets the axis a few mm off the tube's
            centre and every r0 grows with it; a model trained at one view read that as force (colon seed
            131, 191 degrees: 7.6 N at rest; docs/results.md).
        subset: all points, or top_bottom_20 (the top and bottom 20% by object z on the first frame).
        clip_frames: frames per clip (T).
        stride: frames between clip starts.
        num_points: ground-truth points drawn per recording (source ground_truth).
        cloud_points: points drawn from the tissue cloud per frame (input cloud).
        image_size: side of the square images (rgb, depth), pixels.
        fps: frame rate for velocities; None: measured from the training recordings.
        seed: seed of the point draws.
        canonical_side: mirror across the object's XZ plane every recording whose first frame shows
            the y < 0 flank (y of points and force negated); beyond the paper.
        mirror_augment: in training, mirror each clip across the object's XZ plane with probability
            1/2 (the y of every token vector and Fy negated): the tube hanging under gravity is
            symmetric about that plane, so a mirrored clip is a valid clip; beyond the paper.
        rotate_augment: in training, turn each clip about the object's Z axis by a uniform random angle (the
            x, y of every token vector and Fx, Fy with it): the tube is nearly round, so a view of another
            part of its circumference is nearly a valid clip; beyond the paper.
        tilt_augment_deg: in training, express each clip's tokens in an object frame tilted by up to this
            many degrees about a random axis across Z (about the tissue's free end), the force unchanged: the
            estimated axis errs by a few degrees (it follows the tube's sag), and a new view can make the
            same error cost more (docs/results.md); 0 = off. Features in `TILTABLE_FEATURES`; beyond the
            paper.
    """

    input: Input = "tracks"
    source: Source = "processed"
    frame: Frame = "object"
    features: Features = "pos_vel"
    subset: Subset = "all"
    radius: Radius = "mm"
    clip_frames: int = 16
    stride: int = 4
    num_points: int = 256
    cloud_points: int = 256
    image_size: int = 112
    fps: float | None = None
    seed: int = 0
    canonical_side: bool = False
    mirror_augment: bool = False
    rotate_augment: bool = False
    tilt_augment_deg: float = 0.0

    def __post_init__(self) -> None:
        # jsonargparse checks the Literal types on the command line; this checks them in Python too
        choices = {"input": Input, "source": Source, "frame": Frame, "features": Features, "subset": Subset,
                   "radius": Radius}
        for name, kind in choices.items():
            allowed = get_args(kind)
            if getattr(self, name) not in allowed:
                raise VisionForceError(f"{name} '{getattr(self, name)}' is not one of {', '.join(allowed)}")
        if self.clip_frames < 1 or self.stride < 1:
            raise VisionForceError("clip_frames and stride must be positive")
        if self.tilt_augment_deg < 0 or (self.tilt_augment_deg and self.features not in TILTABLE_FEATURES):
            raise VisionForceError(f"tilt_augment_deg {self.tilt_augment_deg}: an angle >= 0, for features "
                                   f"{', '.join(TILTABLE_FEATURES)}")
        if self.radius == "tissue" and (not self.features.startswith("polar") or self.frame != "object"
                                        or self.tilt_augment_deg):
            raise VisionForceError("radius 'tissue' scales the polar features' r0 (features polar_..., frame "
                                   "object), and a tilt needs r0 in mm (tilt_augment_deg 0)")
        for name in ("canonical_side", "mirror_augment", "rotate_augment", "tilt_augment_deg"):
            if getattr(self, name) and (self.input != "tracks" or self.frame != "object"):
                raise VisionForceError(f"{name} moves tracked points in the object frame (input tracks, frame "
                                       "object): the camera frame does not know the object's symmetries")

    @property
    def input_key(self) -> str:
        """The batch key of the model input: tokens, images or depth."""
        return INPUT_KEYS[self.input]

    @property
    def channels(self) -> int:
        """Channels per point token (point inputs); clouds carry positions only."""
        return 3 if self.input == "cloud" else FEATURE_CHANNELS[self.features]

    def with_fps(self, fps: float) -> ClipSpec:
        return ClipSpec(**{**self.to_dict(), "fps": float(fps)})

    def to_dict(self) -> dict[str, Any]:
        """Plain values (for checkpoints, which load with torch.load(weights_only=True))."""
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> ClipSpec:
        """A spec from saved values; unknown keys (other data-module options) are ignored."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in names and v is not None or k == "fps"})
