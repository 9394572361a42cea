"""How much an object frame's error costs the forces, per test view (docs/results.md, "The hardest view:
`colon_s7` at 60°"). On a simulated dataset's processed recordings, `vfmodels.networks.ridge` on VisionForce's tokens
(seconds to train) is fitted and tested with each recording's tracks expressed in

- `ours`: the estimated object frame (what the pipeline uses),
- `true`: the simulator's frame (`ground_truth/object_frame.json`),
- `true_rotation` / `true_origin`: one of the two taken from the simulator, the other ours,
- `tilted`: ours, with training copies whose frame is tilted at random (`--copies` per training recording, up
  to `--tilt-deg` about an axis across Z): an augmentation that would teach the model a frame's error.

Prints, per mode, every validation and test recording's RMS error over the three components (N): the square
root of the mean squared error over Fx, Fy and Fz, which weighs the largest component most; the experiment's
tables give the avg RMSE (the mean of the three components' RMSEs), which is lower where Fz dominates.

    python bench/study_frame_error.py results/colon_s7/manifests/groundtruth.manifest.yaml
    python bench/study_frame_error.py results/colon_s7/manifests/klt.manifest.yaml --modes ours tilted
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from vfdata.clips.decode import Decoded, decoded_tracks, force_at
from vfdata.clips.tokens import tilt_about
from vfdata.manifest import ManifestEntry, load_manifest
from vfdata.recording.derived import DerivedRecording
from vfmodels.experiment.ridge_run import config_spec
from vfmodels.networks.ridge import RidgeForceModel

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "visionforce.yaml"
MODES = ("ours", "true", "true_rotation", "true_origin", "tilted")


class Tracks:
    """One recording's tracks in the camera frame (mm), its estimated and true frames, its force (N)."""

    def __init__(self, entry: ManifestEntry):
        self.entry = entry
        with DerivedRecording.open(entry.processed) as derived:
            frame, tracks = derived.object_frame, derived.tracks()
        self.times_ns, self.visible = tracks.times_ns, tracks.visible
        self.camera_mm = tracks.points_object_mm @ frame.rotation.T + frame.origin
        self.ours = (frame.rotation, frame.origin)
        truth = json.loads((entry.raw / "ground_truth" / "object_frame.json").read_text())
        self.true = (np.asarray(truth["rotation"]), np.asarray(truth["origin_mm"]))
        self.force_n = force_at(entry, tracks.times_ns)

    def decoded(self, spec, rotation: np.ndarray, origin: np.ndarray) -> Decoded:
        return decoded_tracks(spec, self.times_ns, (self.camera_mm - origin) @ rotation, self.visible,
                              self.force_n, rotation, origin)

    def frame(self, mode: str) -> tuple[np.ndarray, np.ndarray]:
        return {"ours": self.ours, "tilted": self.ours, "true": self.true,
                "true_rotation": (self.true[0], self.ours[1]), "true_origin": (self.ours[0], self.true[1])}[mode]


def tilted(rotation: np.ndarray, rng: np.random.Generator, max_deg: float) -> np.ndarray:
    """The frame turned by up to `max_deg` about a random axis across its Z (the training augmentation's
    `tilt_about`; the axis from a 2D normal draw, as the figures in docs/results.md were drawn)."""
    x, y = rng.normal(size=2)
    return rotation @ tilt_about(np.arctan2(y, x), np.radians(max_deg * rng.uniform()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("manifest", type=Path, help="a manifest whose processed files are simulated recordings'")
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    parser.add_argument("--tilt-deg", type=float, default=8.0)
    parser.add_argument("--copies", type=int, default=4)
    args = parser.parse_args()
    manifest = load_manifest(args.manifest)
    spec = config_spec(CONFIG)
    tracks = {e.id: Tracks(e) for e in manifest.entries}
    split = {s: [e.id for e in manifest.split(s)] for s in ("train", "val", "test")}
    for mode in args.modes:
        decoded = {i: t.decoded(spec, *t.frame(mode)) for i, t in tracks.items()}
        train = [decoded[i] for i in split["train"]]
        if mode == "tilted":
            rng = np.random.default_rng(0)
            for i in split["train"]:
                for _ in range(args.copies):
                    rotation, origin = tracks[i].ours
                    train.append(tracks[i].decoded(spec, tilted(rotation, rng, args.tilt_deg), origin))
        model = RidgeForceModel(mirror=spec.mirror_augment, rotate=spec.rotate_augment)
        model.fit(train, [decoded[i] for i in split["val"]])
        cells = []
        for i in split["val"] + split["test"]:
            error = model.predict(decoded[i]) - decoded[i].force_n
            error = error[np.isfinite(error).all(axis=1)]
            cells.append(f"{i} ({tracks[i].entry.orientation_deg:.0f}°) {np.sqrt((error ** 2).mean()):.3f}")
        print(f"{mode:>13}: " + "  ".join(cells), flush=True)


if __name__ == "__main__":
    main()
