"""The tracker's hand-written gradients and optimiser against torch's autograd and torch.optim.Adam."""

import math

import numpy as np
import pytest
import torch

from vfdata.tracking.adam import Adam
from vfdata.tracking.llr import llr_residual, nearest_neighbours, normal_matrix, reconstruction_weights
from vfdata.tracking.losses import chamfer_term, flow_term
from vfdata.tracking.siren import Siren


def autograd_siren(siren: Siren, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """The same network written plainly with autograd leaves: (output, [W1, b1, W2, b2, ...])."""
    leaves = []
    for weight, bias in zip(siren.weights, siren.biases, strict=True):
        leaves += [weight.clone().requires_grad_(), bias.clone().requires_grad_()]
    h = x
    for layer in range(len(siren.weights)):
        h = h @ leaves[2 * layer].T + leaves[2 * layer + 1]
        if layer < len(siren.weights) - 1:
            h = torch.sin(siren.omega_0 * h)
    return h, leaves


@pytest.mark.parametrize("hidden_layers", [1, 2, 3])
def test_siren_gradient_equals_autograd(hidden_layers):
    generator = torch.Generator().manual_seed(hidden_layers)
    siren = Siren(3, 3, 32, hidden_layers, omega_0=30.0, generator=generator, dtype=torch.float64)
    x = torch.rand(200, 3, generator=generator, dtype=torch.float64) * 2 - 1
    upstream = torch.randn(200, 3, generator=generator, dtype=torch.float64)

    output, cache = siren.forward(x)
    gradient = siren.backward(cache, upstream).clone()

    reference, leaves = autograd_siren(siren, x)
    assert torch.allclose(output, reference, rtol=0, atol=1e-12)
    (reference * upstream).sum().backward()
    expected = torch.cat([leaf.grad.reshape(-1) for leaf in leaves])
    assert gradient.shape == siren.parameters.shape
    assert torch.allclose(gradient, expected, rtol=1e-10, atol=1e-10)
    # A second backward pass overwrites the gradient rather than adding to it.
    assert torch.allclose(siren.backward(cache, upstream), expected, rtol=1e-10, atol=1e-10)


def test_siren_initialisation_follows_the_paper_and_the_seed():
    siren = Siren(3, 3, 64, 2, omega_0=30.0, generator=torch.Generator().manual_seed(0))
    first, hidden, out = siren.weights
    assert first.shape == (64, 3) and hidden.shape == (64, 64) and out.shape == (3, 64)
    assert first.abs().max() <= 1 / 3 and first.abs().max() > 0.3  # U(-1/fan_in, 1/fan_in)
    bound = math.sqrt(6 / 64) / 30
    assert hidden.abs().max() <= bound and hidden.abs().max() > 0.9 * bound
    assert out.abs().max() <= bound
    again = Siren(3, 3, 64, 2, omega_0=30.0, generator=torch.Generator().manual_seed(0))
    other = Siren(3, 3, 64, 2, omega_0=30.0, generator=torch.Generator().manual_seed(1))
    assert torch.equal(siren.parameters, again.parameters)
    assert not torch.equal(siren.parameters, other.parameters)
    with pytest.raises(ValueError):
        Siren(hidden_layers=0)


def test_adam_matches_torch_optim_adam_step_by_step():
    generator = torch.Generator().manual_seed(0)
    start = torch.randn(500, generator=generator)
    ours = Adam(start.clone(), lr=3e-3)
    theirs_param = start.clone().requires_grad_()
    theirs = torch.optim.Adam([theirs_param], lr=3e-3)
    for _ in range(25):
        gradient = torch.randn(500, generator=generator) * 10 ** torch.randn(1, generator=generator)
        ours.step(gradient)
        theirs_param.grad = gradient.clone()
        theirs.step()
        assert torch.allclose(ours.parameters, theirs_param.detach(), rtol=1e-6, atol=1e-7)
    assert not torch.allclose(ours.parameters, start)


def _points(seed, n=300):
    rng = np.random.default_rng(seed)
    uv = rng.uniform(-10, 10, (n, 2))
    return np.column_stack([uv, 80 + 0.03 * uv[:, 0] ** 2 + rng.normal(0, 0.2, n)])


def test_chamfer_gradient_equals_autograd():
    moved = torch.from_numpy(_points(1))
    nearest = torch.from_numpy(_points(3))
    value, gradient = chamfer_term(moved.clone(), nearest)
    p = moved.clone().requires_grad_()
    expected = (p - nearest).square().sum(dim=1).mean()
    expected.backward()
    assert torch.allclose(value, expected.detach(), rtol=1e-12)
    assert torch.allclose(gradient, p.grad, rtol=1e-10, atol=1e-12)


def test_llr_normal_matrix_gives_the_gradient_of_the_llr_term():
    rest_points = _points(0)
    neighbours = nearest_neighbours(rest_points, 8)
    weights = reconstruction_weights(rest_points, neighbours)
    matrix = normal_matrix(neighbours, weights)
    assert np.allclose(matrix, matrix.T)
    moved = torch.from_numpy(rest_points + np.random.default_rng(1).normal(0, 0.5, rest_points.shape))

    p = moved.clone().requires_grad_()
    t_neighbours, t_weights = torch.from_numpy(neighbours), torch.from_numpy(weights)
    rest = llr_residual(torch.from_numpy(rest_points), t_neighbours, t_weights)
    term = (llr_residual(p, t_neighbours, t_weights) - rest).square().sum(dim=1).mean()
    term.backward()
    n = len(rest_points)
    gradient = 2.0 / n * matrix @ (moved.numpy() - rest_points)
    assert np.allclose(gradient, p.grad.numpy(), rtol=1e-9, atol=1e-12)
    # ... and its value, as the quadratic form.
    difference = moved.numpy() - rest_points
    assert np.isclose(np.sum(difference * (matrix @ difference)) / n, term.item(), rtol=1e-9)


def test_flow_gradient_equals_autograd():
    rng = np.random.default_rng(4)
    points = torch.from_numpy(_points(5, 100))
    fx, fy, cx, cy = 520.0, 515.0, 320.0, 240.0
    uv = torch.stack([fx * points[:, 0] / points[:, 2] + cx, fy * points[:, 1] / points[:, 2] + cy], dim=1)
    target = uv + torch.from_numpy(rng.normal(0, 3, (100, 2)))
    mm_per_px = points[:, 2] / fx
    value, gradient = flow_term(points, target, mm_per_px, fx, fy, cx, cy)

    p = points.clone().requires_grad_()
    z = p[:, 2].clamp_min(1e-3)
    projected = torch.stack([fx * p[:, 0] / z + cx, fy * p[:, 1] / z + cy], dim=1)
    expected = ((projected - target) * mm_per_px[:, None]).square().sum(dim=1).mean()
    expected.backward()
    assert torch.allclose(value, expected.detach(), rtol=1e-12)
    assert torch.allclose(gradient, p.grad, rtol=1e-10, atol=1e-12)
