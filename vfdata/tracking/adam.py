"""Adam (Kingma and Ba, 2015) on one flat parameter tensor, updated in place.

The same update as `torch.optim.Adam` without weight decay or AMSGrad (tests/test_tracking_siren.py
compares them step by step), but on a single tensor: the tracker's SIREN keeps all its parameters in
one, so a step is six tensor operations instead of a loop over parameter groups and tensors.
"""

from __future__ import annotations

import math

import torch


class Adam:
    """Adam state for `parameters` (a flat tensor, updated in place by `step`)."""

    def __init__(
        self,
        parameters: torch.Tensor,
        lr: float = 1e-3,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ):
        self.parameters = parameters
        self.lr = float(lr)
        self.beta1, self.beta2 = (float(b) for b in betas)
        self.eps = float(eps)
        self.steps = 0
        self._mean = torch.zeros_like(parameters)  # first moment of the gradient
        self._square = torch.zeros_like(parameters)  # second moment

    def step(self, gradient: torch.Tensor) -> None:
        self.steps += 1
        self._mean.lerp_(gradient, 1.0 - self.beta1)
        self._square.mul_(self.beta2).addcmul_(gradient, gradient, value=1.0 - self.beta2)
        bias_correction1 = 1.0 - self.beta1**self.steps
        bias_correction2 = 1.0 - self.beta2**self.steps
        denominator = self._square.sqrt().div_(math.sqrt(bias_correction2)).add_(self.eps)
        self.parameters.addcdiv_(self._mean, denominator, value=-self.lr / bias_correction1)
