"""SIREN: a multilayer perceptron with sine activations (Sitzmann et al., NeurIPS 2020).

Layer l computes sin(omega_0 * (W x + b)). Initialisation as in the paper: the first layer's weights
are uniform in [-1/fan_in, 1/fan_in], every later layer's in [-sqrt(6/fan_in)/omega_0,
sqrt(6/fan_in)/omega_0], which keeps pre-activations standard-normal-like through depth so that
inputs in [-1, 1] give omega_0 / pi periods over that range in the first layer. The output layer is
linear with the same initialisation as the hidden layers.
"""

from __future__ import annotations

import math

import torch
from torch import nn


class SineLayer(nn.Module):
    def __init__(self, in_features: int, out_features: int, omega_0: float, first: bool):
        super().__init__()
        self.omega_0 = float(omega_0)
        self.linear = nn.Linear(in_features, out_features)
        bound = 1.0 / in_features if first else math.sqrt(6.0 / in_features) / self.omega_0
        with torch.no_grad():
            self.linear.weight.uniform_(-bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sin(self.omega_0 * self.linear(x))


class Siren(nn.Module):
    """in_features -> `hidden_layers` sine layers of width `hidden_features` -> linear out_features."""

    def __init__(
        self,
        in_features: int = 3,
        out_features: int = 3,
        hidden_features: int = 64,
        hidden_layers: int = 2,
        omega_0: float = 30.0,
    ):
        super().__init__()
        if hidden_layers < 1:
            raise ValueError("a SIREN needs at least one sine layer")
        layers: list[nn.Module] = [SineLayer(in_features, hidden_features, omega_0, first=True)]
        for _ in range(hidden_layers - 1):
            layers.append(SineLayer(hidden_features, hidden_features, omega_0, first=False))
        out = nn.Linear(hidden_features, out_features)
        bound = math.sqrt(6.0 / hidden_features) / omega_0
        with torch.no_grad():
            out.weight.uniform_(-bound, bound)
        layers.append(out)
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)
