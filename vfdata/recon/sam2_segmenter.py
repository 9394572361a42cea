"""The `sam2` segmenter: Meta's SAM2 video predictor from the user's local config and checkpoint."""

from __future__ import annotations

import tempfile
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from vfdata.errors import BackendError, InputError
from vfdata.recon.prompt import Prompt
from vfdata.recon.segmenter import Segmenter
from vfdata.weights import load_state_dict


class Sam2Segmenter(Segmenter):
    """Adapter over the `sam2` package's video predictor (Ravi et al., 2024), from a local model
    config (e.g. configs/sam2.1/sam2.1_hiera_l.yaml, as the package names it) and checkpoint.

    SAM2 propagates over a whole video held in memory, so this backend works on `segment_video`;
    `start` segments a single frame and `track` refuses (re-propagating per frame would be
    quadratic in the video length)."""

    name = "sam2"

    def __init__(
        self, config: str | None = None, checkpoint: str | Path | None = None, *, device: str = "cuda"
    ):
        if config is None or checkpoint is None:
            raise BackendError(
                "sam2: needs config=<model config, e.g. configs/sam2.1/sam2.1_hiera_l.yaml> and "
                "checkpoint=<sam2.1_hiera_large.pt>; the weights cannot be downloaded by vfdata"
            )
        checkpoint = Path(checkpoint).expanduser()
        if not checkpoint.is_file():
            raise BackendError(f"sam2: checkpoint {checkpoint} not found")
        # Read by us, tensors only, before the package is imported: older sam2 releases call
        # torch.load without weights_only.
        state = load_state_dict(checkpoint, "SAM2 checkpoint")
        try:  # an optional package, installed by the user with its weights
            from sam2.build_sam import build_sam2_video_predictor
        except ImportError as exc:
            raise BackendError(
                f"sam2: the 'sam2' package is not installed ({exc}); "
                "pip install it from github.com/facebookresearch/sam2"
            ) from exc
        try:  # without a checkpoint: the package builds the model only, and we load the weights
            self._predictor = build_sam2_video_predictor(config, None, device=device)
        except Exception as exc:  # hydra/config errors come in many types
            raise BackendError(f"sam2: cannot build the predictor from {config}: {exc}") from exc
        try:
            self._predictor.load_state_dict(state)
        except RuntimeError as exc:
            raise BackendError(f"sam2: {checkpoint} does not fit {config}: {str(exc).splitlines()[0]}") from exc
        self.config, self.checkpoint, self.device = config, checkpoint, device
        self._frames: list[np.ndarray] = []
        self._masks: list[np.ndarray] = []

    def parameters(self) -> dict:
        return {"backend": self.name, "config": self.config, "checkpoint": str(self.checkpoint)}

    def segment_video(
        self, frames: Iterable[np.ndarray], prompt: Prompt, depths: Iterable[np.ndarray] | None = None
    ) -> list[np.ndarray]:
        import torch  # present when sam2 is; local so that importing vfdata stays light

        frames = list(frames)
        if not frames:
            return []
        h, w = frames[0].shape[:2]
        prompt.check_inside(w, h)
        with tempfile.TemporaryDirectory(prefix="vfdata-sam2-") as folder:
            # The predictor reads a folder of JPEG frames named by index.
            for i, frame in enumerate(frames):
                cv2.imwrite(str(Path(folder) / f"{i:06d}.jpg"), frame, [cv2.IMWRITE_JPEG_QUALITY, 95])
            with torch.inference_mode():
                state = self._predictor.init_state(video_path=folder)
                points = list(prompt.positive) + list(prompt.negative)
                labels = [1] * len(prompt.positive) + [0] * len(prompt.negative)
                self._predictor.add_new_points_or_box(
                    inference_state=state,
                    frame_idx=0,
                    obj_id=1,
                    points=np.array(points, np.float32) if points else None,
                    labels=np.array(labels, np.int32) if points else None,
                    box=np.array(prompt.box, np.float32) if prompt.box is not None else None,
                )
                masks: list[np.ndarray | None] = [None] * len(frames)
                for idx, _obj_ids, logits in self._predictor.propagate_in_video(state):
                    masks[idx] = (logits[0, 0] > 0).cpu().numpy()
        if masks[0] is None or not masks[0].any():
            raise InputError(
                "prompt", "the first frame's mask is empty: the prompt does not cover the tissue"
            )
        return [m if m is not None else np.zeros((h, w), bool) for m in masks]

    def start(self, image: np.ndarray, prompt: Prompt, depth_mm: np.ndarray | None = None) -> np.ndarray:
        self._frames = [image]
        self._masks = self.segment_video(self._frames, prompt)
        return self._masks[0]

    def track(self, image: np.ndarray, depth_mm: np.ndarray | None = None) -> np.ndarray:
        # Re-propagating per frame would be quadratic; SAM2 is meant for segment_video.
        raise BackendError("sam2: propagates over a whole video; use segment_video(frames, prompt)")
