"""How unlike the training frames a frame's input is: the Mahalanobis distance of its embedding (the
per-frame output of a causal model's `encode_frames`) from the training frames' embeddings.

The band (`vfmodels.evaluation.band.stretch`) widens with it: on views the model has not learnt, the
errors grow where validation cannot show it, and the set encoder's output moves away from everything
training gave it (docs/results.md, "How sure"). The reference is the training frames' mean and precision
(inverse covariance, with `RIDGE` on its diagonal so that a direction the training frames never vary in
does not make every other frame infinitely far), taken with the weights being validated.

Torch tensors in and out, on the model's device.
"""

from __future__ import annotations

import torch

RIDGE = 1e-6  # added to the covariance's diagonal (embedding units squared)
MIN_FRAMES_PER_DIM = 2  # fewer training frames than this per embedding dimension: no reference


def reference(z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(mean (D,), precision (D, D)) of training embeddings z (M, D), in float64; None when there are too
    few frames to estimate a covariance (`MIN_FRAMES_PER_DIM`)."""
    z = z.detach().reshape(-1, z.shape[-1]).double()
    z = z[torch.isfinite(z).all(dim=1)]
    if len(z) < MIN_FRAMES_PER_DIM * z.shape[1]:
        return None
    mean = z.mean(dim=0)
    cov = torch.cov(z.T) + RIDGE * torch.eye(z.shape[1], dtype=z.dtype, device=z.device)
    return mean, torch.linalg.inv(cov)


def distance(z: torch.Tensor, mean: torch.Tensor, precision: torch.Tensor) -> torch.Tensor:
    """The Mahalanobis distance of embeddings z (..., D) from the reference: (...) in z's dtype."""
    d = z.double() - mean
    return torch.einsum("...i,ij,...j->...", d, precision, d).clamp(min=0).sqrt().to(z.dtype)
