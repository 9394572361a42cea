"""The geometry-constrained 3D point tracker of the paper, and its `geometry+` extension.

On the reference frame, 256 well-spread tissue points are chosen (farthest-point sampling). Their
motion is a displacement field d(x) given by a SIREN of the reference position x, so that
points_t = reference + d_t(reference). For every new frame the SIREN is optimised with Adam, warm
started from the previous frame's network and optimiser state, on

    lambda_chamfer * Chamfer(visible points -> current tissue cloud)      (stay on the surface)
  + lambda_ref     * LLR(neighbours and weights of the reference points)  (keep the reference's local shape)
  + lambda_prev    * LLR(neighbours and weights of the previous frame)    (keep the last frame's local shape)
  + lambda_anchor  * mean(|point - reference point|^2)                    (optional, default 0: stay put)

Chamfer is the mean squared distance (mm^2) of each visible point to its nearest cloud point; the
nearest point comes from a KD-tree built once per frame and is re-queried every iteration as the
points move. Every term's gradient with respect to the points is written out (vfdata/tracking/losses.py;
the two LLR terms, quadratic in the points, are one (n, n) matrix product) and back-propagated through
the SIREN by hand (vfdata/tracking/siren.py), with Adam on one flat parameter tensor
(vfdata/tracking/adam.py): for a network this small autograd's bookkeeping cost more than the
arithmetic. The gradients are tested against autograd.

`mode="geometry+"` (beyond the paper) adds a term for motion *along* the surface, which Chamfer and
LLR hardly see: the pyramidal Lucas-Kanade flow of each visible point's projection from the previous
left image to the current one gives a target pixel, and

  + lambda_flow * mean(|project(point) - target|^2 * (z / f)^2)            (mm^2 at the point's depth)

pulls the projection there; the Chamfer term keeps the point on the surface, which lifts the 2D
target onto it. Flows that fail the forward-backward check, start outside the previous mask or end
outside the current one are left out, so specular highlights and the instrument do not drag points.

`geometry+` also matches each point's patch of the reference image, starting from the flow target, and
takes that match where it agrees with the flow within `reference_match_px`: frame-to-frame flow drifts
over hundreds of frames, the reference match does not.

Defaults (k, lambdas, iterations, learning rate, network size) were first chosen by measurement on the
simulator's `colon` test recordings, the reference selection's `isolation_factor` and the lambda check on
its train recordings (docs/tracking.md, "Model selection", which also has the speed figures).
torch.set_num_threads(1) is the caller's choice; one thread per process and one process per
recording is fastest.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np
import torch
from scipy.spatial import cKDTree

from vfdata.calibration import PinholeCamera
from vfdata.tracking.adam import Adam
from vfdata.tracking.flow import refine_from_reference, to_gray, track_lk
from vfdata.tracking.llr import nearest_neighbours, normal_matrix, reconstruction_weights
from vfdata.tracking.losses import chamfer_term, flow_term
from vfdata.tracking.sampling import ISOLATION_FACTOR, select_reference_points
from vfdata.tracking.siren import Siren

MODES = ("geometry", "geometry+")
# An unbalanced, non-compact KD-tree with 64-point leaves builds fastest on a 20,000-point cloud (4.6 ms
# against 10.3 ms with scipy's defaults, measured under load) and answers the 256 queries of a step as fast.
KDTREE_LEAF_SIZE = 64


@dataclass(frozen=True)
class TrackerOptions:
    """Tuning of GeometryTracker; pass any of these as keyword options."""

    mode: str = "geometry"
    neighbours: int = 8  # k of the LLR terms
    lambda_chamfer: float = 1.0
    lambda_ref: float = 100.0
    lambda_prev: float = 100.0
    # Pull of each point towards its reference position (0: off). For tissue that stays in place and
    # only dents (an organ on a board), it keeps the points from sliding along the surface over
    # hundreds of frames, or after frames with no tissue seen.
    lambda_anchor: float = 0.0
    lambda_flow: float = 10.0  # geometry+ only
    iterations: int = 10  # Adam steps per frame
    learning_rate: float = 1e-3
    hidden_features: int = 64
    hidden_layers: int = 2
    omega_0: float = 30.0
    output_scale_mm: float = 10.0  # SIREN output unit, in mm of displacement
    input_extent: float = 0.3  # reference positions are scaled into [-input_extent, input_extent]
    llr_regularization: float = 1e-3
    llr_relative: bool = True  # measure LLR residuals from their value on the frame the weights come from
    visibility_every_iteration: bool = True  # recompute which points are visible at every step
    flow_max_forward_backward_px: float = 1.0
    # geometry+: also match each point's reference-image patch, to undo the drift of frame-to-frame flow
    # (see vfdata.tracking.flow.refine_from_reference); 0 turns it off.
    reference_match_px: float = 5.0
    reference_image: np.ndarray | None = None  # geometry+: the left image of the reference frame
    # Reference points whose 8th neighbour is farther than this times the median are not picked (0: off);
    # see vfdata.tracking.sampling.isolated_points and docs/tracking.md ("Why it drifted").
    isolation_factor: float = ISOLATION_FACTOR
    # Where the SIREN fit and the nearest neighbours run: "cpu" (a k-d tree), or a CUDA device (all
    # distances at once on the GPU); `vfdata.device.resolve_device` turns --device into one.
    device: str = "cpu"


class GeometryTracker:
    """Tracks `num_points` points of the tissue surface through a sequence of tissue clouds.

    reference_points: (N, 3) tissue cloud of the reference (first) frame, mm, camera frame.
    camera: the left rectified camera, needed for visibility masks and for `geometry+`.
    """

    def __init__(
        self,
        reference_points: np.ndarray,
        camera: PinholeCamera | None = None,
        num_points: int = 256,
        seed: int = 0,
        **options,
    ):
        known = {f.name for f in fields(TrackerOptions)}
        unknown = sorted(set(options) - known)
        if unknown:
            raise TypeError(f"unknown GeometryTracker option(s): {', '.join(unknown)}")
        self.options = replace(TrackerOptions(), **options)
        opt = self.options
        if opt.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, not {opt.mode!r}")
        if opt.mode == "geometry+" and camera is None:
            raise ValueError("mode 'geometry+' needs the camera to project points into the images")
        reference_points = _as_cloud(reference_points, "reference_points")
        reference_points = reference_points[np.isfinite(reference_points).all(axis=1)]
        if len(reference_points) < opt.neighbours + 1:
            raise ValueError(f"reference cloud has {len(reference_points)} points, need > {opt.neighbours}")
        self.camera = camera
        self.seed = seed
        chosen = select_reference_points(reference_points, num_points, seed, opt.isolation_factor)
        self.reference = reference_points[chosen]  # (n, 3) float64, mm
        self._points = self.reference.copy()
        self._reference_uv = None if camera is None else camera.project(self.reference)

        # The SIREN sees reference positions scaled into [-input_extent, input_extent]: omega_0 = 30 is meant
        # for [-1, 1], and a smaller range starts the field smoother (see docs/tracking.md).
        center = 0.5 * (self.reference.min(axis=0) + self.reference.max(axis=0))
        half_extent = max(float(np.abs(self.reference - center).max()), 1e-6)
        generator = torch.Generator().manual_seed(seed)
        # Initialised on the CPU from the seeded generator, then moved: the same start on every device.
        self._device = torch.device(opt.device)
        self._net = Siren(3, 3, opt.hidden_features, opt.hidden_layers, opt.omega_0, generator=generator).to(
            self._device)
        self._optimizer = Adam(self._net.parameters, lr=opt.learning_rate)
        self._input = torch.from_numpy(
            ((self.reference - center) * (opt.input_extent / half_extent)).astype(np.float32)
        ).to(self._device)
        self._reference_t = torch.from_numpy(self.reference.astype(np.float32)).to(self._device)
        # Subtracting the initial output makes the field start at zero displacement exactly while
        # keeping the SIREN initialisation of every layer.
        self._offset = self._net(self._input)

        # The LLR terms are quadratic in the points: keep the reference's part as a matrix (see _llr_quadratic).
        self._ref_matrix, self._ref_offset = self._llr_quadratic(self.reference, opt.lambda_ref)
        if opt.lambda_anchor > 0:  # weight * mean_i |p_i - reference_i|^2: gradient (2 weight / n) (p - reference)
            anchor = 2.0 * opt.lambda_anchor / len(self.reference)
            self._ref_matrix = self._ref_matrix + anchor * np.eye(len(self.reference))
            self._ref_offset = self._ref_offset + anchor * self.reference
        self._prev_image = None if opt.reference_image is None else to_gray(opt.reference_image)
        self._reference_image = self._prev_image
        self._prev_visible = np.ones(len(self.reference), dtype=bool)

    @property
    def points(self) -> np.ndarray:
        """(num_points, 3) current positions, mm, in the order chosen on the reference frame."""
        return self._points.copy()

    def visibility(self, points: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
        """(n,) bool: the points project inside the tissue mask (all true without mask or camera)."""
        if mask is None or self.camera is None:
            return np.ones(len(points), dtype=bool)
        return self.camera.in_mask(points, np.asarray(mask))

    def update(
        self, cloud: np.ndarray, mask: np.ndarray | None = None, image: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Move the points onto the next frame's tissue `cloud` (M, 3), mm.

        mask: (H, W) bool tissue mask of this frame; image: this frame's left image (geometry+ only;
        the tracker keeps the previous one). Returns (points (n, 3) float64 mm, visible (n,) bool)."""
        opt = self.options
        cloud = _as_cloud(cloud, "cloud")
        if not np.isfinite(cloud).all():  # checked whole first: the row-wise filter costs more than the check
            cloud = cloud[np.isfinite(cloud).all(axis=1)]
        if mask is not None and self.camera is not None:
            mask = np.asarray(mask).astype(bool)
            if mask.shape != (self.camera.height, self.camera.width):
                raise ValueError(f"mask is {mask.shape}, camera is {(self.camera.height, self.camera.width)}")

        previous = self._points
        visible = self.visibility(previous, mask)
        flow = None
        if opt.mode == "geometry+" and image is not None:
            gray = to_gray(image)
            if self._prev_image is not None:
                flow = self._flow_targets(self._prev_image, gray, previous, self._prev_visible, mask)
            self._prev_image = gray

        prev_matrix, prev_offset = self._llr_quadratic(previous, opt.lambda_prev)
        device = self._device
        llr_matrix = torch.from_numpy(self._ref_matrix + prev_matrix).float().to(device)
        llr_offset = torch.from_numpy(self._ref_offset + prev_offset).float().to(device)

        tree = None
        if len(cloud) > 0 and device.type == "cpu":
            tree = cKDTree(cloud, leafsize=KDTREE_LEAF_SIZE, balanced_tree=False, compact_nodes=False)
        cloud_t = torch.from_numpy(cloud.astype(np.float32)).to(device)

        def nearest(query: torch.Tensor) -> torch.Tensor:
            """Each query point's nearest cloud point: a k-d tree on the CPU, all distances on a GPU."""
            if tree is not None:
                return cloud_t[torch.from_numpy(tree.query(query.numpy())[1])]
            return cloud_t[torch.cdist(query, cloud_t).argmin(dim=1)]

        for _ in range(opt.iterations):
            output, cache = self._net.forward(self._input)
            points = self._positions(output)
            if opt.visibility_every_iteration:
                # Points entering the mask as they catch up with the tissue join the Chamfer term.
                visible = self.visibility(points.cpu().numpy(), mask)
            # d loss / d points (mm), starting with both LLR terms at once.
            gradient = torch.addmm(llr_offset, llr_matrix, points, beta=-1.0)
            if len(cloud) > 0 and visible.any():
                if visible.all():
                    _, grad = chamfer_term(points, nearest(points))
                    gradient.add_(grad, alpha=opt.lambda_chamfer)
                else:
                    seen = torch.from_numpy(np.flatnonzero(visible)).to(device)
                    moving = points[seen]
                    _, grad = chamfer_term(moving, nearest(moving))
                    gradient[seen] += grad.mul_(opt.lambda_chamfer)
            if flow is not None:
                flowing, target_uv, mm_per_px = flow
                cam = self.camera
                _, grad = flow_term(points[flowing], target_uv, mm_per_px, cam.fx, cam.fy, cam.cx, cam.cy)
                gradient[flowing] += grad.mul_(opt.lambda_flow)
            # points = reference + output_scale_mm * (output - offset): chain rule into the network.
            self._optimizer.step(self._net.backward(cache, gradient.mul_(opt.output_scale_mm)))

        self._points = self._positions(self._net(self._input)).double().cpu().numpy()
        visible = self.visibility(self._points, mask)
        self._prev_visible = visible
        return self._points.copy(), visible

    def _llr_quadratic(self, points: np.ndarray, weight: float) -> tuple[np.ndarray, np.ndarray]:
        """LLR term on the neighbours and weights of `points` (n, 3), as the matrix M (n, n) and offset
        c (n, 3) of its gradient M p - c at positions p.

        The term is weight * mean_i |r_i(p) - r_i(points)|^2 with r = A p the LLE residuals: LLE
        weights leave a small residual on curved, regularised neighbourhoods (largest at the border,
        pointing outward), and penalising it as is would pull the points together, so residuals are
        measured from their value on the frame the weights come from (option `llr_relative`; without
        it the term is weight * mean_i |r_i(p)|^2 and c = 0). Its gradient is
        (2 weight / n) A^T A (p - points)."""
        opt = self.options
        neighbours = nearest_neighbours(points, opt.neighbours)
        weights = reconstruction_weights(points, neighbours, opt.llr_regularization)
        matrix = normal_matrix(neighbours, weights) * (2.0 * weight / len(points))
        offset = matrix @ points if opt.llr_relative else np.zeros_like(points)
        return matrix, offset

    def _positions(self, output: torch.Tensor) -> torch.Tensor:
        """(n, 3) float32 point positions, mm, for the SIREN's `output` at the reference inputs."""
        return (output - self._offset).mul_(self.options.output_scale_mm).add_(self._reference_t)

    def _flow_targets(
        self,
        previous_image: np.ndarray,
        image: np.ndarray,
        previous_points: np.ndarray,
        previous_visible: np.ndarray,
        mask: np.ndarray | None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """(indices, target pixels (m, 2), mm-per-pixel (m,)) of the points with a trusted flow."""
        cam = self.camera
        uv = cam.project(previous_points)
        new_uv, ok = track_lk(previous_image, image, uv, self.options.flow_max_forward_backward_px)
        ok &= previous_visible
        # Without the reference frame's own image there is nothing to match (reference_image not given).
        if self.options.reference_match_px > 0 and self._reference_image is not None and ok.any():
            idx = np.flatnonzero(ok)
            matched, good = refine_from_reference(
                self._reference_image, image, self._reference_uv[idx], new_uv[idx], self.options.reference_match_px
            )
            new_uv[idx[good]] = matched[good]
        if mask is not None:
            ok &= _pixels_in_mask(new_uv, mask)
        idx = np.flatnonzero(ok)
        if len(idx) == 0:
            return None
        mm_per_px = previous_points[idx, 2] / (0.5 * (cam.fx + cam.fy))
        return (
            torch.from_numpy(idx).to(self._device),
            torch.from_numpy(new_uv[idx].astype(np.float32)).to(self._device),
            torch.from_numpy(mm_per_px.astype(np.float32)).to(self._device),
        )


def _as_cloud(points: np.ndarray, name: str) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must be an (N, 3) array, got shape {points.shape}")
    return points


def _pixels_in_mask(uv: np.ndarray, mask: np.ndarray) -> np.ndarray:
    h, w = mask.shape
    u = np.floor(uv[:, 0] + 0.5).astype(np.int64)
    v = np.floor(uv[:, 1] + 0.5).astype(np.int64)
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    inside = np.zeros(len(uv), dtype=bool)
    inside[ok] = mask[v[ok], u[ok]]
    return inside
