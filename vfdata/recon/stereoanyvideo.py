"""The `stereoanyvideo` depth backend: Stereo Any Video (Jing et al., 2025), the paper's stereo
model, from the user's local checkout of its code and a downloaded checkpoint."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from vfdata.errors import BackendError
from vfdata.recon.depth_estimator import DepthEstimator
from vfdata.weights import load_state_dict


class StereoAnyVideoDepth(DepthEstimator):
    """Adapter for Stereo Any Video (Jing et al., 2025), the paper's stereo model.

    `code` is the user's local checkout of the model's repository (the folder holding `models/`;
    it is imported as the package `stereoanyvideo`, as the repository's own code expects), and
    `checkpoint` the downloaded weights (e.g. StereoAnyVideo_MIX.pth). Frames are processed in clips
    of `clip_length` with half-clip overlap, as the authors' evaluation does; `disparity` on a single
    pair runs a one-frame clip."""

    name = "stereoanyvideo"

    def __init__(
        self,
        code: str | Path | None = None,
        checkpoint: str | Path | None = None,
        *,
        device: str = "cuda",
        iters: int = 20,
        clip_length: int = 20,
    ):
        if code is None or checkpoint is None:
            raise BackendError(
                "stereoanyvideo: needs code=<local checkout of github.com/TomTomTommi/stereoanyvideo> and "
                "checkpoint=<StereoAnyVideo_MIX.pth>; the weights cannot be downloaded by vfdata"
            )
        code, checkpoint = Path(code).expanduser(), Path(checkpoint).expanduser()
        if not (code / "models" / "core" / "stereoanyvideo.py").is_file():
            raise BackendError(
                f"stereoanyvideo: {code} is not a Stereo Any Video checkout "
                "(no models/core/stereoanyvideo.py)"
            )
        if not checkpoint.is_file():
            raise BackendError(f"stereoanyvideo: checkpoint {checkpoint} not found")
        # Read before any model code is imported: tensors only, nothing in the file runs.
        state = load_state_dict(checkpoint, "Stereo Any Video checkpoint")
        # torch is imported here, not at the top: `vfdata` starts without it unless a network runs.
        import torch

        self._torch = torch
        self.device = device
        self.iters = iters
        self.clip_length = clip_length
        self._code, self._checkpoint = code, checkpoint
        # The repository imports itself as `stereoanyvideo.models...`: put its parent on the path
        # under that name.
        parent = code.resolve().parent
        if code.resolve().name != "stereoanyvideo":
            raise BackendError(
                f"stereoanyvideo: the checkout folder must be named 'stereoanyvideo' (its modules import "
                f"themselves by that name), not '{code.name}'"
            )
        if str(parent) not in sys.path:
            sys.path.insert(0, str(parent))
        try:
            module = importlib.import_module("stereoanyvideo.models.core.stereoanyvideo")
        except ImportError as exc:
            raise BackendError(f"stereoanyvideo: cannot import the model code from {code}: {exc}") from exc
        model = module.StereoAnyVideo(mixed_precision=False)
        try:
            model.load_state_dict(state, strict=True)
        except RuntimeError as exc:
            first_line = str(exc).splitlines()[0]
            raise BackendError(f"stereoanyvideo: {checkpoint} does not fit the model: {first_line}") from exc
        self._model = model.to(device).eval()

    def parameters(self) -> dict:
        return {
            "backend": self.name,
            "code": str(self._code),
            "checkpoint": str(self._checkpoint),
            "iters": self.iters,
            "clip_length": self.clip_length,
        }

    def disparity(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        return self.disparity_video([left], [right])[0]

    def disparity_video(self, lefts: Sequence[np.ndarray], rights: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Disparities of a whole stereo video, clip by clip (the model is temporal)."""
        n = len(lefts)
        stride = max(1, self.clip_length // 2)
        out: list[np.ndarray | None] = [None] * n
        for start in range(0, n, stride):
            stop = min(start + self.clip_length, n)
            clip = self._run_clip(lefts[start:stop], rights[start:stop])
            # Keep the middle of overlapping clips (each frame from the clip where it is most central).
            keep_from = 0 if start == 0 else stride // 2
            for i in range(keep_from, stop - start):
                out[start + i] = clip[i]
            if stop == n:
                break
        return out  # type: ignore[return-value]

    def _run_clip(self, lefts: Sequence[np.ndarray], rights: Sequence[np.ndarray]) -> list[np.ndarray]:
        torch = self._torch

        def video(images: Sequence[np.ndarray]):
            rgb = [
                cv2.cvtColor(im, cv2.COLOR_BGR2RGB) if im.ndim == 3 else cv2.cvtColor(im, cv2.COLOR_GRAY2RGB)
                for im in images
            ]
            return torch.from_numpy(np.stack(rgb)).permute(0, 3, 1, 2).float()  # (T, 3, H, W), 0..255

        left_v, right_v = video(lefts), video(rights)
        h, w = left_v.shape[-2:]
        # The network needs sizes divisible by 32: pad symmetrically by edge replication.
        ph, pw = (-h) % 32, (-w) % 32
        pads = (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2)
        left_v = torch.nn.functional.pad(left_v, pads, mode="replicate")
        right_v = torch.nn.functional.pad(right_v, pads, mode="replicate")
        with torch.no_grad():
            flow = self._model(
                left_v[None].to(self.device), right_v[None].to(self.device), iters=self.iters, test_mode=True
            )  # (T, B, 2, H, W): the x component is minus the disparity
        disp = flow[:, 0, 0].abs().float().cpu().numpy()
        disp = disp[:, pads[2] : pads[2] + h, pads[0] : pads[0] + w]
        return [d.astype(np.float32) for d in disp]

