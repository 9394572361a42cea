"""The two image backbones of the baselines, written here so that the project needs neither
torchvision nor timm (a CPU-only torch cannot have torchvision: PyPI's wheels are built against the
CUDA torch, and timm depends on torchvision).

- `R3D18`: the 3D ResNet-18 of Tran et al. 2018 ("A closer look at spatiotemporal convolutions for
  action recognition", R3D): ResNet-18 (He et al. 2016) with every convolution a full 3x3x3 one in
  time and space; stem (3, 7, 7) with stride (1, 2, 2); stages 2-4 halve time and space.
- `ViTSmall16`: the Vision Transformer encoder (Dosovitskiy et al. 2021) in the "Small" size of
  Touvron et al. 2021 (DeiT): 16 x 16 px patches, width 384, 12 pre-norm blocks of 6 heads, MLP 1536;
  the class token after the last LayerNorm is the image's feature.

Parameter names and shapes are those of torchvision's `r3d_18()` and timm's `vit_small_patch16_224`,
so checkpoints saved from either (Kinetics-400, ImageNet) load as they are; `adapt_vit_state` fits
RGB ViT weights to one input channel and another image size. tests/test_models_baselines.py compares
names, shapes and outputs with both packages where they are installed.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

# ----------------------------------------------------------------------------------------- R3D-18


def _conv_norm(c_in: int, c_out: int, kernel: int | tuple[int, int, int], stride: int | tuple[int, int, int],
               padding: int | tuple[int, int, int], relu: bool) -> nn.Sequential:
    """Conv3d (no bias: the BatchNorm after it shifts) -> BatchNorm3d [-> ReLU]."""
    layers: list[nn.Module] = [nn.Conv3d(c_in, c_out, kernel, stride, padding, bias=False), nn.BatchNorm3d(c_out)]
    if relu:
        layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


class ResidualBlock3D(nn.Module):
    """He et al.'s basic block in 3D: two 3x3x3 convolutions plus a shortcut, ReLU after the sum.
    `stride` applies to time and space alike; the shortcut is then a strided 1x1x1 projection."""

    def __init__(self, c_in: int, c_out: int, stride: int = 1):
        super().__init__()
        self.conv1 = _conv_norm(c_in, c_out, 3, stride, 1, relu=True)
        self.conv2 = _conv_norm(c_out, c_out, 3, 1, 1, relu=False)
        self.downsample = None
        if stride != 1 or c_in != c_out:
            self.downsample = _conv_norm(c_in, c_out, 1, stride, 0, relu=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shortcut = x if self.downsample is None else self.downsample(x)
        return F.relu(self.conv2(self.conv1(x)) + shortcut)


class R3D18(nn.Module):
    """Clips (B, 3, T, H, W) -> class scores (B, num_classes); `forward_features` gives the last stage's
    (B, 512, T/8, H/16, W/16) (sizes rounded up). Two blocks per stage, widths 64-128-256-512."""

    def __init__(self, num_classes: int = 400):
        super().__init__()
        # The stem halves space only (temporal stride 1); the first block of stages 2-4 halves time
        # and space, so time goes T -> T/2 -> T/4 -> T/8.
        self.stem = _conv_norm(3, 64, (3, 7, 7), (1, 2, 2), (1, 3, 3), relu=True)
        self.layer1 = nn.Sequential(ResidualBlock3D(64, 64), ResidualBlock3D(64, 64))
        self.layer2 = nn.Sequential(ResidualBlock3D(64, 128, stride=2), ResidualBlock3D(128, 128))
        self.layer3 = nn.Sequential(ResidualBlock3D(128, 256, stride=2), ResidualBlock3D(256, 256))
        self.layer4 = nn.Sequential(ResidualBlock3D(256, 512, stride=2), ResidualBlock3D(512, 512))
        self.fc = nn.Linear(512, num_classes)
        for module in self.modules():
            if isinstance(module, nn.Conv3d):  # He et al. 2015 for ReLU networks
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")

    def forward_features(self, x: torch.Tensor) -> torch.Tensor:
        x = self.stem(x)
        return self.layer4(self.layer3(self.layer2(self.layer1(x))))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(self.forward_features(x).mean(dim=(2, 3, 4)))


# ------------------------------------------------------------------------------------- ViT-S/16


class PatchEmbedding(nn.Module):
    """Images (B, C, H, W) -> tokens (B, (H/p)(W/p), D): each p x p patch projected linearly, which a
    convolution with kernel = stride = p does."""

    def __init__(self, in_chans: int, dim: int, patch: int):
        super().__init__()
        self.proj = nn.Conv2d(in_chans, dim, patch, stride=patch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


class SelfAttention(nn.Module):
    """Multi-head self-attention; one Linear gives queries, keys and values, its outputs ordered
    (q|k|v, head, channel) as the pretrained checkpoints store them."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, d = x.shape
        q, k, v = self.qkv(x).view(b, n, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, k, v)  # softmax(q k^T / sqrt(d / heads)) v per head
        return self.proj(out.transpose(1, 2).reshape(b, n, d))


class FeedForward(nn.Module):
    """Linear -> GELU (exact) -> Linear, applied to each token."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class EncoderBlock(nn.Module):
    """Pre-norm transformer block: x + attn(LN(x)), then x + mlp(LN(x))."""

    def __init__(self, dim: int, heads: int, hidden: int):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = SelfAttention(dim, heads)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = FeedForward(dim, hidden)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class ViTSmall16(nn.Module):
    """Images (B, in_chans, img_size, img_size) -> the class token's feature (B, 384), or class scores
    (B, num_classes) when `num_classes` > 0 (a Linear head on that feature).

    The patch grid is img_size // 16 a side (pixels beyond the last whole patch are not seen); the
    position embedding is learnt for that grid, one entry per patch plus one for the class token."""

    patch = 16
    num_features = 384
    depth = 12
    heads = 6

    def __init__(self, img_size: int = 224, in_chans: int = 3, num_classes: int = 0):
        super().__init__()
        if img_size < self.patch:
            raise ValueError(f"img_size {img_size} is smaller than one {self.patch} px patch")
        self.img_size = img_size
        self.in_chans = in_chans
        self.grid = img_size // self.patch
        dim = self.num_features
        self.patch_embed = PatchEmbedding(in_chans, dim, self.patch)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + self.grid**2, dim))
        self.blocks = nn.Sequential(*(EncoderBlock(dim, self.heads, 4 * dim) for _ in range(self.depth)))
        self.norm = nn.LayerNorm(dim, eps=1e-6)
        self.head = nn.Linear(dim, num_classes) if num_classes > 0 else nn.Identity()
        # Random start as usual for ViTs: small truncated-normal weights, zero biases, a near-zero class token.
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)
        for module in self.modules():
            if isinstance(module, nn.Linear):
                nn.init.trunc_normal_(module.weight, std=0.02)
                nn.init.zeros_(module.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if tuple(x.shape[-2:]) != (self.img_size, self.img_size):
            size = tuple(x.shape[-2:])
            raise ValueError(f"ViT-S/16 built for {self.img_size} x {self.img_size} px images got {size}")
        tokens = self.patch_embed(x)
        tokens = torch.cat([self.cls_token.expand(len(tokens), -1, -1), tokens], dim=1) + self.pos_embed
        return self.head(self.norm(self.blocks(tokens))[:, 0])


def resample_position_embedding(pos_embed: torch.Tensor, grid: int) -> torch.Tensor:
    """A (1, 1 + g*g, D) position embedding of a square g x g patch grid -> (1, 1 + grid*grid, D): the
    class token's entry kept, the patches' resampled as a D-channel g x g image (bicubic, antialiased
    when shrinking, so that a small grid averages its area rather than picking isolated entries).
    Returned unchanged when it is already for `grid`, or when its patch part is not square."""
    cls, patches = pos_embed[:, :1], pos_embed[:, 1:]
    old = math.isqrt(patches.shape[1])
    if old == grid or old * old != patches.shape[1]:
        return pos_embed
    image = patches.float().reshape(1, old, old, -1).permute(0, 3, 1, 2)
    image = F.interpolate(image, size=(grid, grid), mode="bicubic", align_corners=False, antialias=True)
    patches = image.permute(0, 2, 3, 1).reshape(1, grid * grid, -1).to(pos_embed.dtype)
    return torch.cat([cls, patches], dim=1)


def adapt_vit_state(state: dict[str, torch.Tensor], model: ViTSmall16) -> dict[str, torch.Tensor]:
    """A ViT-S/16 checkpoint's tensors fitted to `model`: the classifier (`head.*`, `pre_logits.*`)
    dropped, RGB patch filters summed over their channels for a one-channel model (a grey image in all
    three channels then gives the same response), the position embedding resampled to the model's grid.
    Anything else is left as it is, for the load to judge."""
    state = {k: v for k, v in state.items() if not k.startswith(("head.", "pre_logits."))}
    weight = state.get("patch_embed.proj.weight")
    if model.in_chans == 1 and weight is not None and weight.ndim == 4 and weight.shape[1] != 1:
        state["patch_embed.proj.weight"] = weight.float().sum(dim=1, keepdim=True).to(weight.dtype)
    if "pos_embed" in state and state["pos_embed"].ndim == 3:
        state["pos_embed"] = resample_position_embedding(state["pos_embed"], model.grid)
    return state
