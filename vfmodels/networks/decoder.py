"""Parts shared by the force models: one head per force component, and the causal LSTM over per-frame
embeddings used by the proposed model and the depth baseline."""

from __future__ import annotations

import torch
from torch import nn


class ForceHeads(nn.Module):
    """(..., D) -> (..., 3): an independent Linear-ReLU-Linear head for each of Fx, Fy, Fz. The
    components differ by up to an order of magnitude in range on tissue; separate heads keep one
    component's gradients from shaping the others' last layers."""

    def __init__(self, in_features: int, hidden: int = 64):
        super().__init__()
        self.heads = nn.ModuleList(
            nn.Sequential(nn.Linear(in_features, hidden), nn.ReLU(), nn.Linear(hidden, 1)) for _ in range(3)
        )

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return torch.cat([head(h) for head in self.heads], dim=-1)


class CausalForceDecoder(nn.Module):
    """Per-frame embeddings (B, T, D) -> per-frame forces (B, T, 3), normalised units. A one-layer
    unidirectional LSTM carries the history of the clip, so frame t depends only on frames <= t; `run`
    also returns the LSTM state after the last frame, from which a stream carries on."""

    def __init__(self, in_features: int, hidden_size: int = 192, head_hidden: int = 64):
        super().__init__()
        self.lstm = nn.LSTM(in_features, hidden_size, num_layers=1, batch_first=True)
        self.heads = ForceHeads(hidden_size, head_hidden)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.run(z)[0]

    def run(self, z: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor] | None = None
            ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """(forces (B, T, 3), the LSTM's (h, c) after frame T-1), starting from `state` (None: zeros)."""
        h, state = self.lstm(z, state)
        return self.heads(h), state
