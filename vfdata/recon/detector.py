"""A prompt source: the paper's fine-tuned Faster R-CNN tissue detector (torchvision)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from vfdata.errors import BackendError, InputError
from vfdata.recon.prompt import Prompt
from vfdata.recon.segmenter import check_image
from vfdata.weights import load_state_dict


@dataclass
class DetectorPrompt:
    """A prompt source: torchvision Faster R-CNN (ResNet-50 FPN) with the user's fine-tuned weights,
    as in the paper; the best-scoring box of the first frame becomes the prompt.

    `weights` is a state dict saved from `fasterrcnn_resnet50_fpn(num_classes=...)` (optionally
    under a "model" or "state_dict" key); `label` is the tissue class id."""

    weights: str | Path | None = None
    num_classes: int = 2
    label: int = 1
    min_score: float = 0.5
    min_size: int = 800  # torchvision's input rescaling (shorter side), as in training
    device: str = "cpu"
    _model: object = field(default=None, init=False, repr=False)

    def __post_init__(self):
        if self.weights is None:
            raise BackendError(
                "detector: needs weights=<fine-tuned Faster R-CNN state dict (.pth)>; "
                "no pretrained tissue detector can be downloaded by vfdata"
            )
        path = Path(self.weights).expanduser()
        if not path.is_file():
            raise BackendError(f"detector: weights {path} not found")
        # Read before torchvision builds anything: tensors only, nothing in the file runs.
        state = load_state_dict(path, "detector weights file")
        # torchvision (and torch) load here, not at the top: `vfdata` starts without them, and torchvision
        # is an optional extra (its PyPI wheels need the CUDA torch; with a CPU torch its import fails).
        try:
            from torchvision.models.detection import fasterrcnn_resnet50_fpn
        except (ImportError, RuntimeError) as exc:
            raise BackendError(
                f"detector: needs torchvision (pip install 'visionforce[detector]', matching your torch): "
                f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
            ) from None

        model = fasterrcnn_resnet50_fpn(
            weights=None, weights_backbone=None, num_classes=self.num_classes, min_size=self.min_size
        )
        try:
            model.load_state_dict(state)
        except RuntimeError as exc:
            raise BackendError(
                f"detector: {path} does not fit Faster R-CNN with {self.num_classes} classes: "
                f"{str(exc).splitlines()[0]}"
            ) from exc
        self._model = model.to(self.device).eval()

    def __call__(self, image: np.ndarray) -> Prompt:
        """The best box of class `label` on this (BGR) frame."""
        import torch  # loaded with the model in __post_init__; local so that importing vfdata stays light

        check_image(image)
        rgb = torch.from_numpy(cv2.cvtColor(image, cv2.COLOR_BGR2RGB)).permute(2, 0, 1).float() / 255
        with torch.no_grad():
            out = self._model([rgb.to(self.device)])[0]  # type: ignore[operator]
        keep = (out["labels"] == self.label) & (out["scores"] >= self.min_score)
        if not bool(keep.any()):
            raise InputError("detector", f"no tissue box with score >= {self.min_score} on the first frame")
        best = int(torch.argmax(torch.where(keep, out["scores"], torch.zeros_like(out["scores"]))))
        h, w = image.shape[:2]
        x0, y0, x1, y1 = out["boxes"][best].tolist()
        return Prompt.from_box([max(0.0, x0), max(0.0, y0), min(float(w), x1), min(float(h), y1)])
