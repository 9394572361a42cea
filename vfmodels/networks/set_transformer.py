"""The proposed force model: a Set Transformer (Lee et al. 2019) per frame over the tracked points,
then a causal LSTM over the clip and one head per force component.

Shapes: B clips, T frames, N points, C features per point (e.g. x, y, z in mm and vx, vy, vz in mm/s,
normalised by the training statistics before they get here).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vfmodels.networks.decoder import CausalForceDecoder


class MultiheadAttentionBlock(nn.Module):
    """MAB(X, Y) = LN(H + rFF(H)), H = LN(X + Multihead(X, Y, Y)), as defined by Lee et al. 2019.

    Multihead projects queries, keys and values, attends per head with fused scaled dot-product
    attention and projects the concatenated heads back (W^O). rFF is one row-wise Linear + ReLU, as in
    the authors' reference implementation. Keys marked invalid take no part in the attention.
    """

    def __init__(self, dim: int, heads: int, layer_norm: bool = True):
        super().__init__()
        if dim % heads:
            raise ValueError(f"dim {dim} is not divisible by heads {heads}")
        self.heads = heads
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.out = nn.Linear(dim, dim)
        self.ff = nn.Sequential(nn.Linear(dim, dim), nn.ReLU())
        self.norm_attn = nn.LayerNorm(dim) if layer_norm else nn.Identity()
        self.norm_ff = nn.LayerNorm(dim) if layer_norm else nn.Identity()

    def _split(self, x: torch.Tensor) -> torch.Tensor:
        b, n, d = x.shape
        return x.view(b, n, self.heads, d // self.heads).transpose(1, 2)

    def _block_diagonal(self, x: torch.Tensor) -> torch.Tensor:
        """(B, Nk, D) -> (B, D, heads * Nk): head h's slice of x, transposed, in diagonal block h."""
        b, n, d = x.shape
        eye = torch.eye(self.heads, dtype=x.dtype, device=x.device)
        return torch.einsum("bnhc,hg->bhcgn", x.view(b, n, self.heads, d // self.heads), eye).reshape(b, d, -1)

    def _attend_few_keys(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Multihead attention of many queries to few keys (an ISAB's points to its inducing points),
        unmasked, as two batched matrix products over all heads at once: (B, Nq, D)."""
        b, nq, d = q.shape
        scores = torch.bmm(q, self._block_diagonal(k)) * (d // self.heads) ** -0.5  # (B, Nq, heads * Nk)
        weights = scores.view(b, nq, self.heads, -1).softmax(dim=-1).view(b, nq, -1)
        return torch.bmm(weights, self._block_diagonal(v).transpose(1, 2))

    def forward(self, x: torch.Tensor, y: torch.Tensor, y_valid: torch.Tensor | None = None) -> torch.Tensor:
        """x (Bx, Nq, D) queries, Bx = B or 1 (learned seeds shared by the batch); y (B, Nk, D) keys
        and values; y_valid (B, Nk) bool, True where the key may be attended to. Returns (B, Nq, D)."""
        batch = y.shape[0]
        q = self.q(x).expand(batch, -1, -1)
        k, v = self.kv(y).chunk(2, dim=-1)
        if y_valid is None and y.shape[1] * 4 <= x.shape[1] and torch.compiler.is_compiling():
            # Same attention, other arithmetic: per-head products of 256 queries x 16 keys x 16 channels
            # are too small for the CPU flash kernel (38 ms a batch of 16 clips, one thread, bf16); two
            # block-diagonal products over all heads compile to 20 ms. Eager, the kernel stays faster.
            o = self._attend_few_keys(q, k, v)
        else:
            mask = None if y_valid is None else y_valid[:, None, None, :]
            o = F.scaled_dot_product_attention(self._split(q), self._split(k), self._split(v), attn_mask=mask)
            o = o.transpose(1, 2).reshape(batch, x.shape[1], -1)
        h = self.norm_attn(x + self.out(o))
        return self.norm_ff(h + self.ff(h))


class InducedSetAttentionBlock(nn.Module):
    """ISAB_m(X) = MAB(X, MAB(I, X)) with m learned inducing points I: O(N m) instead of O(N^2), and
    equivariant to the order of X. Invalid points are masked as keys of the first MAB; their own
    outputs are computed but never read as keys downstream."""

    def __init__(self, dim: int, heads: int, inducing_points: int, layer_norm: bool = True):
        super().__init__()
        self.inducing = nn.Parameter(torch.empty(1, inducing_points, dim))
        nn.init.xavier_uniform_(self.inducing)
        self.summarise = MultiheadAttentionBlock(dim, heads, layer_norm)
        self.broadcast = MultiheadAttentionBlock(dim, heads, layer_norm)

    def forward(self, x: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        h = self.summarise(self.inducing, x, valid)
        return self.broadcast(x, h)


class PoolingByMultiheadAttention(nn.Module):
    """PMA_k(Z) = MAB(S, rFF(Z)) with k learned seeds S: invariant to the order of Z."""

    def __init__(self, dim: int, heads: int, seeds: int = 1, layer_norm: bool = True):
        super().__init__()
        self.seeds = nn.Parameter(torch.empty(1, seeds, dim))
        nn.init.xavier_uniform_(self.seeds)
        self.ff = nn.Sequential(nn.Linear(dim, dim), nn.ReLU())
        self.pool = MultiheadAttentionBlock(dim, heads, layer_norm)

    def forward(self, z: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        return self.pool(self.seeds, self.ff(z), valid)


class SetTransformerLSTM(nn.Module):
    """Point tokens (B, T, N, C) [+ valid (B, T, N)] -> forces (B, T, 3) in normalised units.

    Per frame: Linear(C -> dim), `isab_blocks` ISABs, PMA with one seed -> z_t (dim). Over the clip:
    a one-layer unidirectional LSTM and three independent heads (Fx, Fy, Fz). The output is invariant
    to the order of the N points and causal in time (frame t sees frames <= t only).

    The reference implementation of the causal interface (`vfmodels.training.regressor`): `encode_frames` (each
    frame on its own) and `decode_frames` (the LSTM, carrying its state), which prediction and the live
    estimator run through `ForceRegressor`.

    Invalid points (not visible, or padding) are zeroed and masked as attention keys. A frame with no
    valid point at all is encoded as a set of all-zero tokens (a fixed "nothing visible" embedding)
    rather than an attention over nothing, which is undefined.

    Args:
        in_features: channels per point token (C): 6 for position + velocity, 3 for one of them, 9 for
            the reference/polar features (ClipSpec.features).
        dim: width of the set encoder.
        heads: attention heads.
        inducing_points: inducing points per ISAB.
        isab_blocks: ISAB blocks per frame.
        layer_norm: layer norm in the attention blocks.
        lstm_hidden: hidden size of the causal LSTM over the clip.
    """

    input_key = "tokens"
    channel_dim = -1

    def __init__(
        self,
        in_features: int = 6,
        dim: int = 64,
        heads: int = 4,
        inducing_points: int = 16,
        isab_blocks: int = 2,
        layer_norm: bool = True,
        lstm_hidden: int = 192,
    ):
        super().__init__()
        self.config = dict(
            in_features=in_features, dim=dim, heads=heads, inducing_points=inducing_points,
            isab_blocks=isab_blocks, layer_norm=layer_norm, lstm_hidden=lstm_hidden,
        )
        self.embed = nn.Linear(in_features, dim)
        self.blocks = nn.ModuleList(
            InducedSetAttentionBlock(dim, heads, inducing_points, layer_norm) for _ in range(isab_blocks)
        )
        self.pool = PoolingByMultiheadAttention(dim, heads, seeds=1, layer_norm=layer_norm)
        self.decoder = CausalForceDecoder(dim, lstm_hidden)

    def encode_frames(self, tokens: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """(B, T, N, C) [+ (B, T, N) bool] -> per-frame embeddings z (B, T, dim)."""
        b, t, n, c = tokens.shape
        x = tokens.reshape(b * t, n, c)
        if valid is not None:
            valid = valid.reshape(b * t, n)
            x = x.masked_fill(~valid[..., None], 0.0)
            # Nothing visible in a frame: attend to the (all-zero) tokens instead of to nothing.
            valid = valid | ~valid.any(dim=1, keepdim=True)
        x = self.embed(x)
        for block in self.blocks:
            x = block(x, valid)
        return self.pool(x, valid).view(b, t, -1)

    def decode_frames(self, z: torch.Tensor, state: tuple | None = None) -> tuple[torch.Tensor, tuple]:
        """Per-frame embeddings (B, T, dim) -> (forces (B, T, 3), the LSTM state after the last frame), from
        `state` (None: the zero state a clip starts from)."""
        return self.decoder.run(z, state)

    def forward(self, tokens: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        return self.decode_frames(self.encode_frames(tokens, valid))[0]
