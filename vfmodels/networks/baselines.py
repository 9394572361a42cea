"""The paper's two image baselines, with the same output as the proposed model: forces (B, T, 3) per
frame in normalised units.

- `RGBResNet3D`: a 3D ResNet-18 (R3D-18, `vfmodels.networks.backbones.R3D18`) on monocular (left) RGB clips.
- `DepthViTLSTM`: a ViT-Small/16 (`vfmodels.networks.backbones.ViTSmall16`, one input channel) per frame on the
  tissue-masked depth image, then the same causal LSTM and heads as the proposed model.

The paper starts both from pretrained weights. Those cannot be downloaded here, so each model takes
`weights_path` (a local file in torchvision's `r3d_18` or timm's `vit_small_patch16_224` format; neither
package is needed to load it) and otherwise starts from random initialisation; `initialisation`
records which, and training logs it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from vfdata.errors import BackendError
from vfmodels.networks.backbones import R3D18, ViTSmall16, adapt_vit_state
from vfmodels.networks.decoder import CausalForceDecoder, ForceHeads

# Kinetics-400 statistics that torchvision's pretrained r3d_18 weights expect (RGB, in [0, 1]).
KINETICS_MEAN = (0.43216, 0.394666, 0.37645)
KINETICS_STD = (0.22803, 0.22145, 0.216989)


def _load_state_dict(path: str | Path, what: str) -> dict[str, torch.Tensor]:
    """A state dict from a local checkpoint file (plain, or wrapped in "state_dict"/"model")."""
    path = Path(path)
    if not path.is_file():
        raise BackendError(f"{path}: {what} weights file not found (pass weights_path=null for random init)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a damaged or non-PyTorch file: say which one
        raise BackendError(f"{path}: cannot read {what} weights ({exc})") from exc
    for key in ("state_dict", "model"):
        if isinstance(state, dict) and isinstance(state.get(key), dict):
            state = state[key]
    if not isinstance(state, dict):
        raise BackendError(f"{path}: not a state dict of {what} weights")
    return state


def _load_checked(module: nn.Module, state: dict[str, torch.Tensor], path: str | Path, what: str,
                  ignore: tuple[str, ...] = ()) -> None:
    """Load `state` into `module`, or a BackendError naming the file when names or shapes differ
    (keys starting with `ignore` may be absent)."""
    own = module.state_dict()
    wrong = [f"{k} {tuple(v.shape)} vs {tuple(own[k].shape)}" for k, v in state.items()
             if k in own and hasattr(v, "shape") and v.shape != own[k].shape]
    if wrong:
        raise BackendError(f"{path}: not {what} weights (shapes differ: {wrong[:3]})")
    missing, unexpected = module.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.startswith(ignore)]
    if missing or unexpected:
        raise BackendError(f"{path}: not {what} weights (missing {missing[:3]}, unexpected {unexpected[:3]})")


NORMS = ("group", "frozen", "batch")


class RGBResNet3D(nn.Module):
    """RGB clips (B, T, 3, H, W), values 0-255 (uint8, or float as `ForceRegressor` passes them on)
    -> forces (B, T, 3).

    R3D-18's stem and four stages give features at T/8 time steps; they are averaged over space,
    interpolated back to the T frames and passed to one head per force component. 3D convolutions
    see both neighbours in time, so unlike the proposed model this baseline is not causal.

    `norm` sets what R3D-18's BatchNorm layers become (docs/models.md, "Baselines"):
    - "group": GroupNorm (32 groups), the same computation in training and evaluation, residual
      branches starting at zero; the default without pretrained weights.
    - "frozen": BatchNorm that always uses its stored statistics (the pretrained weights'; their
      scale and shift still train); the default with `weights_path`.
    - "batch": plain BatchNorm, batch statistics in training and running averages in
      evaluation. Those averages trail the weights by ~10 optimiser steps (momentum 0.1), so an
      evaluation after a few hundred steps can be off by orders of magnitude.

    Args:
        weights_path: a local checkpoint in torchvision's r3d_18 format (Kinetics-400); None: random
            initialisation.
        head_hidden: hidden units of each force head.
        norm: group, frozen or batch (see above); None: frozen with weights, else group.
    """

    input_key = "images"
    channel_dim = 2

    def __init__(self, weights_path: str | None = None, head_hidden: int = 64,
                 norm: Literal["group", "frozen", "batch"] | None = None):
        super().__init__()
        norm = norm or ("frozen" if weights_path else "group")
        if norm not in NORMS:
            raise ValueError(f"norm '{norm}' is not one of {', '.join(NORMS)}")
        # the resolved norm is stored, so that a checkpoint rebuilds the same layers without the weights file
        self.config = dict(weights_path=weights_path, head_hidden=head_hidden, norm=norm)
        self.norm = norm
        backbone = R3D18()
        if weights_path:
            # the Kinetics classifier is not used (the force heads replace it): neither loaded nor required
            state = {k: v for k, v in _load_state_dict(weights_path, "r3d_18").items() if not k.startswith("fc.")}
            _load_checked(backbone, state, weights_path, "r3d_18", ignore=("fc.",))
        if norm == "group":
            _batch_to_group_norm(backbone)
            # Each residual branch starts at zero (its last norm's scale = 0, Goyal et al. 2017), so the
            # untrained network is the stem and the shortcuts. Without it, GroupNorm's per-clip
            # normalisation leaves pooled features that differ between clips by ~1-9% of their size,
            # and a tiny overfit barely moved in 40 steps (loss 1.04 -> 0.97; with it 1.01 -> 0.03).
            for stage in (backbone.layer1, backbone.layer2, backbone.layer3, backbone.layer4):
                for block in stage:
                    nn.init.zeros_(block.conv2[1].weight)
        self.initialisation = f"pretrained:{weights_path}" if weights_path else "random"
        self.features = nn.Sequential(
            backbone.stem, backbone.layer1, backbone.layer2, backbone.layer3, backbone.layer4
        )
        self.heads = ForceHeads(512, head_hidden)
        # Kinetics statistics on the 0-255 scale: the clips arrive as 0-255 whatever their dtype
        self.register_buffer("mean", 255 * torch.tensor(KINETICS_MEAN).view(1, 3, 1, 1, 1), persistent=False)
        self.register_buffer("std", 255 * torch.tensor(KINETICS_STD).view(1, 3, 1, 1, 1), persistent=False)

    def train(self, mode: bool = True) -> RGBResNet3D:
        super().train(mode)
        if self.norm == "frozen":
            for module in self.modules():
                if isinstance(module, nn.BatchNorm3d):
                    module.eval()
        return self

    def forward(self, images: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        t = images.shape[1]
        x = (images.float().transpose(1, 2) - self.mean) / self.std  # (B, 3, T, H, W)
        # PyTorch's CPU bf16 Conv3d backward now and then returns weight gradients of ~1e31 (a bare
        # nn.Conv3d shows it, tests/test_models_baselines.py): training diverged to NaN within 30 steps under
        # bf16-mixed. On the CPU the 3D convolutions therefore run in float32 whatever the autocast.
        with torch.autocast("cpu", enabled=False):  # CPU autocast only: a GPU's stays as it is
            f = self.features(x).mean(dim=(3, 4))  # (B, 512, T')
        f = F.interpolate(f, size=t, mode="linear", align_corners=False)
        return self.heads(f.transpose(1, 2))


def _batch_to_group_norm(module: nn.Module, groups: int = 32) -> None:
    """Replace every BatchNorm3d under `module` by a GroupNorm over the same channels (in place)."""
    for name, child in module.named_children():
        if isinstance(child, nn.BatchNorm3d):
            setattr(module, name, nn.GroupNorm(min(groups, child.num_features), child.num_features))
        else:
            _batch_to_group_norm(child, groups)


class DepthViTLSTM(nn.Module):
    """Masked depth clips (B, T, 1, H, W) (normalised; background = the normalised value of 0 mm) ->
    forces (B, T, 3). ViT-Small's class token per frame (384) -> causal LSTM (192) -> three heads.

    H and W must equal `img_size`. Pretrained RGB ViT weights are adapted to one channel by summing
    the patch-embedding filters over RGB, and the position embedding is resampled to `img_size`.

    Args:
        weights_path: a local ViT-Small/16 checkpoint in timm's vit_small_patch16_224 format (RGB or one
            channel, any square patch grid); None: random initialisation.
        img_size: side of the square depth images (ClipSpec.image_size), pixels.
        lstm_hidden: hidden size of the causal LSTM over the clip.
    """

    input_key = "depth"
    channel_dim = 2

    def __init__(self, weights_path: str | None = None, img_size: int = 224, lstm_hidden: int = 192):
        super().__init__()
        self.config = dict(weights_path=weights_path, img_size=img_size, lstm_hidden=lstm_hidden)
        self.vit = ViTSmall16(img_size=img_size, in_chans=1)
        if weights_path:
            state = adapt_vit_state(_load_state_dict(weights_path, "vit_small_patch16_224"), self.vit)
            _load_checked(self.vit, state, weights_path, "ViT-Small/16")
        self.initialisation = f"pretrained:{weights_path}" if weights_path else "random"
        self.decoder = CausalForceDecoder(self.vit.num_features, lstm_hidden)

    def forward(self, depth: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        b, t = depth.shape[:2]
        z = self.vit(depth.flatten(0, 1).float()).view(b, t, -1)
        return self.decoder(z)
