"""The `cotracker` baseline: CoTracker3 (Karaev et al., 2024), offline predictor, lifted to 3D.

The model is not bundled: it needs the `cotracker` package (github.com/facebookresearch/co-tracker,
`pip install git+https://github.com/facebookresearch/co-tracker`) and a local checkpoint such as
`scaled_offline.pth` from huggingface.co/facebook/cotracker3. Without either, a clear BackendError is
raised. The offline predictor sees the whole clip at once (keep clips to a few hundred frames on CPU);
the same 256 reference points as the other trackers are its queries on frame 0, and its 2D tracks are
lifted with each frame's depth map. A point is visible when CoTracker calls it visible, it has depth,
and it lies in the tissue mask.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from vfdata.calibration import PinholeCamera
from vfdata.errors import BackendError
from vfdata.tracking.lifting import lift_pixels
from vfdata.tracking.sampling import select_reference_points
from vfdata.weights import load_state_dict

CHECKPOINT_HINT = "download scaled_offline.pth from https://huggingface.co/facebook/cotracker3"


def load_cotracker(checkpoint: str | Path | None, device: str = "cpu", window_len: int = 60) -> torch.nn.Module:
    """The CoTracker3 offline predictor with weights from a local `checkpoint` file."""
    if checkpoint is None:
        raise BackendError(f"cotracker: no checkpoint given ({CHECKPOINT_HINT})")
    path = Path(checkpoint)
    if not path.is_file():
        raise BackendError(f"{path}: CoTracker3 checkpoint not found ({CHECKPOINT_HINT})")
    # Read by us, tensors only, before the package sees the file: its own loader unpickles whatever
    # the file holds (torch.load without weights_only).
    state = load_state_dict(path, "CoTracker3 checkpoint")
    try:  # an optional package, installed by the user with its weights
        from cotracker.predictor import CoTrackerPredictor
    except ImportError as exc:
        raise BackendError(
            "cotracker: the 'cotracker' package is not installed "
            "(pip install git+https://github.com/facebookresearch/co-tracker)"
        ) from exc
    model = CoTrackerPredictor(checkpoint=None, offline=True, window_len=window_len)
    try:
        model.model.load_state_dict(state)
    except RuntimeError as exc:
        raise BackendError(f"{path}: not a CoTracker3 offline checkpoint ({str(exc).splitlines()[0]})") from exc
    return model.to(device).eval()


class CoTrackerTracker:
    """Runs CoTracker3 on a whole clip: `.track(images, depths_mm, masks)` -> ((F, n, 3), (F, n))."""

    def __init__(
        self,
        reference_points: np.ndarray,
        camera: PinholeCamera,
        checkpoint: str | Path | None,
        num_points: int = 256,
        seed: int = 0,
        device: str = "cpu",
        window_len: int = 60,
    ):
        self.model = load_cotracker(checkpoint, device=device, window_len=window_len)
        self.device = device
        self.camera = camera
        reference_points = np.asarray(reference_points, dtype=np.float64)
        reference_points = reference_points[np.isfinite(reference_points).all(axis=1)]
        self.reference = reference_points[select_reference_points(reference_points, num_points, seed=seed)]

    @torch.no_grad()
    def track(
        self, images: np.ndarray, depths_mm: np.ndarray, masks: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """images (F, H, W, 3) uint8 RGB left images, frame 0 = the reference frame; depths_mm (F, H, W);
        masks (F, H, W) bool or None. Returns points (F, n, 3) mm (NaN without depth), visible (F, n)."""
        images = np.asarray(images)
        if images.ndim != 4 or images.shape[-1] != 3:
            raise ValueError(f"images must be (F, H, W, 3) RGB, got {images.shape}")
        uv0 = self.camera.project(self.reference)
        keep = np.isfinite(uv0).all(axis=1)
        video = torch.from_numpy(images).permute(0, 3, 1, 2)[None].float().to(self.device)
        queries = np.concatenate([np.zeros((int(keep.sum()), 1)), uv0[keep]], axis=1)
        queries_t = torch.from_numpy(queries).float()[None].to(self.device)
        tracks, visibility = self.model(video, queries=queries_t)
        tracks = tracks[0].cpu().numpy()  # (F, m, 2)
        visibility = visibility[0].cpu().numpy().astype(bool).reshape(len(images), -1)
        num_frames, n = len(images), len(self.reference)
        uv = np.full((num_frames, n, 2), np.nan)
        uv[:, keep] = tracks
        seen = np.zeros((num_frames, n), dtype=bool)
        seen[:, keep] = visibility
        points = np.stack([lift_pixels(uv[f], depths_mm[f], self.camera) for f in range(num_frames)])
        visible = seen & np.isfinite(points).all(axis=2)
        if masks is not None:
            visible &= np.stack([self.camera.in_mask(points[f], masks[f]) for f in range(num_frames)])
        return points, visible
