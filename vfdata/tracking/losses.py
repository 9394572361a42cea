"""The tracker's loss terms, each as (value, gradient with respect to the points), in closed form.

Every term is a mean of squared lengths over points, in mm^2, so its gradient is short to write down
and costs a few tensor operations; the tracker adds the weighted gradients up and back-propagates them
through the SIREN by hand (vfdata/tracking/siren.py). tests/test_tracking_siren.py checks each
gradient against autograd on random inputs. The LLR terms, quadratic in the points, are a matrix
product in the tracker (`vfdata.tracking.llr.normal_matrix`).

- `chamfer_term`: mean_i |p_i - q_i|^2, q_i the nearest cloud point of p_i (found outside, held fixed,
  as autograd does through a nearest-neighbour index).
- `flow_term`: mean_i |(project(p_i) - target_i) * mm_per_px_i|^2, the distance in the image, scaled to
  mm at the point's depth, to a target pixel.
"""

from __future__ import annotations

import torch

MIN_DEPTH_MM = 1e-3  # projection guard: depths are clamped here (points never get that close to the camera)


def chamfer_term(points: torch.Tensor, nearest: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean squared distance (mm^2) of `points` (m, 3) to their `nearest` cloud points (m, 3)."""
    difference = points - nearest
    value = difference.square().sum() / len(points)
    return value, difference.mul_(2.0 / len(points))


def flow_term(
    points: torch.Tensor,
    target_uv: torch.Tensor,
    mm_per_px: torch.Tensor,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean squared image distance, in mm at the point's depth, of the projections of `points` (m, 3)
    (pinhole fx, fy, cx, cy) to `target_uv` (m, 2) pixels; `mm_per_px` (m,) converts pixels to mm."""
    depth = points[:, 2].clamp_min(MIN_DEPTH_MM)
    u = points[:, 0] / depth * fx + cx
    v = points[:, 1] / depth * fy + cy
    scale = mm_per_px.square()
    error_u, error_v = u - target_uv[:, 0], v - target_uv[:, 1]
    count = len(points)
    value = ((error_u.square() + error_v.square()) * scale).sum() / count
    grad_u = error_u * scale * (2.0 / count)
    grad_v = error_v * scale * (2.0 / count)
    # u = fx x / z + cx: du/dx = fx / z, du/dz = -(u - cx) / z; the same for v with y.
    grad_z = -(grad_u * (u - cx) + grad_v * (v - cy)) / depth
    grad_z = grad_z * (points[:, 2] > MIN_DEPTH_MM)
    gradient = torch.stack([grad_u * fx / depth, grad_v * fy / depth, grad_z], dim=1)
    return value, gradient
