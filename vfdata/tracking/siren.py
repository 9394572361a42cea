"""SIREN: a multilayer perceptron with sine activations (Sitzmann et al., NeurIPS 2020), with a
hand-written forward and backward pass.

Layer l computes sin(omega_0 * (W x + b)); the output layer is linear. Initialisation as in the paper:
the first layer's weights are uniform in [-1/fan_in, 1/fan_in], every later layer's (the output layer's
too) in [-sqrt(6/fan_in)/omega_0, sqrt(6/fan_in)/omega_0], which keeps pre-activations
standard-normal-like through depth. Biases keep the usual linear-layer initialisation,
U(-1/sqrt(fan_in), 1/sqrt(fan_in)), as the paper's code does.

Why by hand: the tracker runs a few optimisation steps of this small network (64 x 2 hidden units,
256 inputs) per video frame, where autograd's graph building and per-op dispatch cost more than the
arithmetic. All parameters live in one flat tensor (`parameters`) and the backward pass writes one
flat gradient (`gradient`), so the optimiser updates everything in a handful of tensor operations.
The gradient equals autograd's (tests/test_tracking_siren.py).
"""

from __future__ import annotations

import math

import torch


class Siren:
    """in_features -> `hidden_layers` sine layers of width `hidden_features` -> linear out_features.

    Parameters are initialised from `generator` (a seeded torch.Generator for reproducible runs; the
    global generator is left alone)."""

    def __init__(
        self,
        in_features: int = 3,
        out_features: int = 3,
        hidden_features: int = 64,
        hidden_layers: int = 2,
        omega_0: float = 30.0,
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        if hidden_layers < 1:
            raise ValueError("a SIREN needs at least one sine layer")
        self.omega_0 = float(omega_0)
        widths = [in_features] + [hidden_features] * hidden_layers + [out_features]
        sizes = [(widths[i + 1], widths[i]) for i in range(len(widths) - 1)]  # (out, in) per layer
        total = sum(o * i + o for o, i in sizes)
        self.parameters = torch.empty(total, dtype=dtype)
        self.gradient = torch.zeros(total, dtype=dtype)
        self.weights, self.biases = _views(self.parameters, sizes)
        self._weight_grads, self._bias_grads = _views(self.gradient, sizes)
        for layer, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            fan_in = weight.shape[1]
            bound = 1.0 / fan_in if layer == 0 else math.sqrt(6.0 / fan_in) / self.omega_0
            weight.uniform_(-bound, bound, generator=generator)
            bias.uniform_(-1.0 / math.sqrt(fan_in), 1.0 / math.sqrt(fan_in), generator=generator)

    def to(self, device: torch.device | str) -> Siren:
        """The network on `device` (parameters and gradient moved, the views rebuilt); self."""
        if self.parameters.device == torch.device(device):
            return self
        sizes = [tuple(w.shape) for w in self.weights]
        self.parameters = self.parameters.to(device)
        self.gradient = self.gradient.to(device)
        self.weights, self.biases = _views(self.parameters, sizes)
        self._weight_grads, self._bias_grads = _views(self.gradient, sizes)
        return self

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return self.forward(x)[0]

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, list[tuple[torch.Tensor, torch.Tensor]]]:
        """(N, in) -> (N, out), plus what `backward` needs: each sine layer's input and pre-activation."""
        cache = []
        for weight, bias in zip(self.weights[:-1], self.biases[:-1], strict=True):
            pre = torch.addmm(bias, x, weight.t()).mul_(self.omega_0)
            cache.append((x, pre))
            x = torch.sin(pre)
        cache.append((x, None))
        return torch.addmm(self.biases[-1], x, self.weights[-1].t()), cache

    def backward(self, cache: list[tuple[torch.Tensor, torch.Tensor]], grad_output: torch.Tensor) -> torch.Tensor:
        """Gradient of a loss with respect to all parameters (flat, in `parameters`' layout), given the
        loss's gradient (N, out) with respect to the output of the `forward` call that made `cache`.
        Overwrites and returns `self.gradient`."""
        grad = grad_output
        for layer in range(len(self.weights) - 1, -1, -1):
            x, _ = cache[layer]
            torch.mm(grad.t(), x, out=self._weight_grads[layer])
            torch.sum(grad, dim=0, out=self._bias_grads[layer])
            if layer == 0:
                break
            # d sin(omega (W x + b)) = omega cos(pre) (W dx + db), for the layer below.
            pre = cache[layer - 1][1]
            grad = torch.mm(grad, self.weights[layer]).mul_(torch.cos(pre)).mul_(self.omega_0)
        return self.gradient


def _views(flat: torch.Tensor, sizes: list[tuple[int, int]]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Weight (out, in) and bias (out,) views into one flat tensor, layer after layer."""
    weights, biases, start = [], [], 0
    for out_features, in_features in sizes:
        weights.append(flat[start : start + out_features * in_features].view(out_features, in_features))
        start += out_features * in_features
        biases.append(flat[start : start + out_features])
        start += out_features
    return weights, biases
