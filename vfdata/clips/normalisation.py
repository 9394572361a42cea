"""Normalisation of model inputs and outputs for plain-PyTorch loops.

The networks (`vfmodels.SetTransformerLSTM`, ...) see normalised inputs and predict normalised forces;
`ForceRegressor` does both conversions itself. In your own loop, take the statistics of the training
split (`ForceClipDataset.normalisation()` or `ForceDataModule.normalisation`, or a checkpoint's
`force_mean` ... buffers) and convert at the edges:

    stats = train.normalisation()
    pred = model(normalise_input(batch["tokens"], stats), batch["valid"])   # normalised units
    force_n = denormalise_force(pred, stats)                                # (B, T, 3) N
"""

from __future__ import annotations

import torch


def _stats(normalisation: dict[str, torch.Tensor], key: str) -> torch.Tensor:
    if key not in normalisation:
        raise KeyError(f"normalisation statistics need '{key}' (from ForceClipDataset.normalisation())")
    return torch.as_tensor(normalisation[key])


def normalise_input(x: torch.Tensor, normalisation: dict[str, torch.Tensor], channel_dim: int = -1) -> torch.Tensor:
    """Inputs (tokens (..., C) or depth (..., 1, H, W) with channel_dim=-3) to the network's units; RGB
    (empty statistics) passes unchanged, as float."""
    mean, std = _stats(normalisation, "input_mean"), _stats(normalisation, "input_std")
    if mean.numel() == 0:
        return x.float()
    shape = [1] * x.ndim
    shape[channel_dim] = -1
    return (x.float() - mean.view(shape).to(x.device)) / std.view(shape).to(x.device)


def normalise_force(force_n: torch.Tensor, normalisation: dict[str, torch.Tensor]) -> torch.Tensor:
    """Forces (..., 3) in N to the network's output units (the training target)."""
    mean, std = _stats(normalisation, "force_mean"), _stats(normalisation, "force_std")
    return (force_n - mean.to(force_n.device)) / std.to(force_n.device)


def denormalise_force(output: torch.Tensor, normalisation: dict[str, torch.Tensor]) -> torch.Tensor:
    """A network's output (..., 3) in normalised units -> force in N."""
    mean, std = _stats(normalisation, "force_mean"), _stats(normalisation, "force_std")
    return output * std.to(output.device) + mean.to(output.device)
