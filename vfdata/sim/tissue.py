"""Geometry of the simulated tissue: a tapered tube with a rounded free end, clamped at its wide end.

Object frame (= the fixture frame; the force sensor frame is the same rotation, shifted back along
-Z): X up (against gravity), Z along the tube axis from the clamp (z = 0) toward the free end,
Y = Z x X. Lengths in mm.

The tube is described twice on the same material parametrisation (s = arc length along the rest
profile in mm, theta = angle around the axis from +X toward +Y):

- a coarse ring mesh of physics nodes (`n_rings` x `n_around`), ring 0 being the clamped one;
- a smooth surface interpolated from the nodes with periodic / clamped Catmull-Rom splines, used
  for rendering (a dense quad grid) and for the ground-truth material points. Both are fixed linear
  maps of the node positions, so every surface sample moves with the material.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

# Spring families of the mass-spring network and their stiffness relative to the membrane modulus.
SPRING_KINDS = ("axial", "hoop", "shear", "bend_axial", "bend_hoop", "cross")


@dataclass(frozen=True)
class TubeShape:
    """Rest (stress-free) shape: a cone frustum from radius `base_radius_mm` at z = 0 to `tip_radius_mm`,
    closed by a hemispherical cap so that the total length is `length_mm`."""

    length_mm: float
    base_radius_mm: float
    tip_radius_mm: float
    n_rings: int = 16
    n_around: int = 12
    cap_rings: int = 3
    cap_angle_deg: float = 72.0

    def __post_init__(self) -> None:
        if self.n_around % 2:
            raise ValueError("n_around must be even (cross springs join opposite nodes)")
        if self.tip_radius_mm >= self.length_mm / 2:
            raise ValueError("tube too short for its cap")


def _ring_profile(shape: TubeShape) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ring axial positions z (mm), radii r (mm) and arc lengths s (mm) along the rest profile."""
    body_len = shape.length_mm - shape.tip_radius_mm
    n_body = shape.n_rings - shape.cap_rings
    z_body = np.linspace(0.0, body_len, n_body)
    r_body = shape.base_radius_mm + (shape.tip_radius_mm - shape.base_radius_mm) * z_body / body_len
    phi = np.radians(np.linspace(0.0, shape.cap_angle_deg, shape.cap_rings + 1)[1:])
    z_cap = body_len + shape.tip_radius_mm * np.sin(phi)
    r_cap = shape.tip_radius_mm * np.cos(phi)
    z = np.concatenate([z_body, z_cap])
    r = np.concatenate([r_body, r_cap])
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(z), np.diff(r)))])
    return z, r, s


def catmull_rom_weights(t: np.ndarray, n: int, periodic: bool) -> tuple[np.ndarray, np.ndarray]:
    """Weights (len(t), n) and their derivatives d/dt of a uniform Catmull-Rom spline through n
    control values at integer parameters 0..n-1, evaluated at the real parameters `t`. Periodic
    (period n) or clamped with linearly extrapolated ghost points at both ends."""
    t = np.asarray(t, dtype=np.float64)
    i = np.floor(t).astype(np.int64)
    if not periodic:
        i = np.clip(i, 0, n - 2)
    f = t - i
    # Catmull-Rom basis for control points i-1, i, i+1, i+2.
    b = np.stack([
        0.5 * (-f**3 + 2 * f**2 - f),
        0.5 * (3 * f**3 - 5 * f**2 + 2),
        0.5 * (-3 * f**3 + 4 * f**2 + f),
        0.5 * (f**3 - f**2),
    ], axis=1)
    db = np.stack([
        0.5 * (-3 * f**2 + 4 * f - 1),
        0.5 * (9 * f**2 - 10 * f),
        0.5 * (-9 * f**2 + 8 * f + 1),
        0.5 * (3 * f**2 - 2 * f),
    ], axis=1)
    w = np.zeros((len(t), n))
    dw = np.zeros((len(t), n))
    rows = np.arange(len(t))
    for k in range(4):
        idx = i + k - 1
        if periodic:
            np.add.at(w, (rows, idx % n), b[:, k])
            np.add.at(dw, (rows, idx % n), db[:, k])
            continue
        # Ghosts: P[-1] = 2 P[0] - P[1], P[n] = 2 P[n-1] - P[n-2].
        for target, scale, mask in (
            (idx, 1.0, (idx >= 0) & (idx < n)),
            (np.zeros_like(idx), 2.0, idx < 0),
            (np.ones_like(idx), -1.0, idx < 0),
            (np.full_like(idx, n - 1), 2.0, idx >= n),
            (np.full_like(idx, n - 2), -1.0, idx >= n),
        ):
            if mask.any():
                np.add.at(w, (rows[mask], target[mask]), scale * b[mask, k])
                np.add.at(dw, (rows[mask], target[mask]), scale * db[mask, k])
    return w, dw


@dataclass(frozen=True)
class SurfaceMap:
    """A fixed linear map from node positions (n_rings, n_around, 3) to surface samples on a tensor
    grid of (s, theta) values: positions = Ws @ X @ Wt^T, plus the two tangents."""

    ws: np.ndarray       # (S, n_rings) axial weights
    dws: np.ndarray      # (S, n_rings) d/ds of the axial weights (1/mm)
    wt: np.ndarray       # (T, n_around) angular weights
    dwt: np.ndarray      # (T, n_around) d/dtheta of the angular weights (1/rad)

    def evaluate(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Node positions (R, C, 3) -> positions, d/ds tangents, d/dtheta tangents, each (S, T, 3)."""
        R, C, _ = nodes.shape
        flat = nodes.reshape(R, C * 3)
        a = (self.ws @ flat).reshape(-1, C, 3)     # along the tube first: (S, C, 3)
        da = (self.dws @ flat).reshape(-1, C, 3)
        return self.wt @ a, self.wt @ da, self.dwt @ a  # then around: (T, C) @ (S, C, 3) -> (S, T, 3)

    def evaluate_scattered(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For a map built from paired (s, theta) samples (S == T): positions and outward unit normals
        (S, 3) of those samples."""
        R, C, _ = nodes.shape
        flat = nodes.reshape(R, C * 3)
        a = (self.ws @ flat).reshape(-1, C, 3)  # matrix products: much faster than einsums
        da = (self.dws @ flat).reshape(-1, C, 3)
        # Per sample, (1 or 2, C) @ (C, 3): positions and d/dtheta together, then d/ds.
        p_pt = np.stack([self.wt, self.dwt], axis=1) @ a
        ps = (self.wt[:, None, :] @ da)[:, 0]
        return p_pt[:, 0], outward_normals(ps, p_pt[:, 1])


def outward_normals(d_ds: np.ndarray, d_dtheta: np.ndarray) -> np.ndarray:
    """Unit outward normals from the two surface tangents (theta runs counter-clockwise about +Z)."""
    n = np.cross(d_dtheta, d_ds)
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)


class Tube:
    """The tube's rest geometry, node masses, spring network and surface maps."""

    def __init__(self, shape: TubeShape, density_kg_m3: float, wall_mm: float):
        self.shape = shape
        self.ring_z, self.ring_r, self.ring_s = _ring_profile(shape)
        self.n_rings, self.n_around = shape.n_rings, shape.n_around
        self.theta = 2 * np.pi * np.arange(self.n_around) / self.n_around
        self.wall_mm = wall_mm
        self.density_kg_m3 = density_kg_m3

    @property
    def n_nodes(self) -> int:
        return self.n_rings * self.n_around

    @property
    def arc_length_mm(self) -> float:
        return float(self.ring_s[-1])

    @cached_property
    def rest_nodes(self) -> np.ndarray:
        """(n_rings, n_around, 3) rest node positions in the object frame (mm)."""
        r = self.ring_r[:, None]
        return np.stack([
            r * np.cos(self.theta)[None, :],
            r * np.sin(self.theta)[None, :],
            np.broadcast_to(self.ring_z[:, None], (self.n_rings, self.n_around)),
        ], axis=-1)

    @cached_property
    def node_mass_kg(self) -> np.ndarray:
        """(n_nodes,) lumped masses: the wall area around each node times wall thickness and density."""
        ds = np.gradient(self.ring_s)
        area_mm2 = ds * 2 * np.pi * self.ring_r / self.n_around
        mass = area_mm2 * self.wall_mm * self.density_kg_m3 * 1e-9
        return np.repeat(mass, self.n_around)

    def node_index(self, ring: np.ndarray | int, k: np.ndarray | int) -> np.ndarray:
        return np.asarray(ring) * self.n_around + np.asarray(k) % self.n_around

    @cached_property
    def springs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(i, j, kind) arrays: node pairs joined by springs and the index of their kind in SPRING_KINDS."""
        R, C = self.n_rings, self.n_around
        rr, cc = np.meshgrid(np.arange(R), np.arange(C), indexing="ij")
        pairs: list[tuple[np.ndarray, np.ndarray, int]] = []

        def add(sel: np.ndarray, dr: int, dc: int, kind: str) -> None:
            a = self.node_index(rr[sel], cc[sel])
            b = self.node_index(rr[sel] + dr, cc[sel] + dc)
            pairs.append((a, b, SPRING_KINDS.index(kind)))

        below = rr < R - 1
        add(below, 1, 0, "axial")
        add(np.ones_like(below), 0, 1, "hoop")
        add(below, 1, 1, "shear")
        add(below, 1, -1, "shear")
        add(rr < R - 2, 2, 0, "bend_axial")
        add(np.ones_like(below), 0, 2, "bend_hoop")
        add(cc < C // 2, 0, C // 2, "cross")
        add(below, 1, C // 2, "cross")
        i = np.concatenate([p[0] for p in pairs])
        j = np.concatenate([p[1] for p in pairs])
        kind = np.concatenate([np.full(len(p[0]), p[2]) for p in pairs])
        return i, j, kind

    @cached_property
    def spring_tributary_mm(self) -> np.ndarray:
        """Width of wall each spring stands for (mm): its share of the membrane it discretises."""
        i, j, kind = self.springs
        ring_i = i // self.n_around
        ring_j = j // self.n_around
        r_mid = 0.5 * (self.ring_r[ring_i] + self.ring_r[ring_j])
        hoop_w = 2 * np.pi * r_mid / self.n_around
        axial_w = np.gradient(self.ring_s)[ring_i]
        names = np.array(SPRING_KINDS)[kind]
        return np.where(np.isin(names, ["axial", "bend_axial", "shear"]), hoop_w, axial_w)

    def s_to_ring(self, s_mm: np.ndarray) -> np.ndarray:
        """Arc length (mm) -> fractional ring index (piecewise linear)."""
        return np.interp(s_mm, self.ring_s, np.arange(self.n_rings, dtype=np.float64))

    def surface_map(self, s_mm: np.ndarray, theta: np.ndarray) -> SurfaceMap:
        """The linear map from nodes to the tensor grid of surface samples at arc lengths `s_mm` and
        angles `theta` (radians)."""
        t_ring = self.s_to_ring(s_mm)
        ws, dws_dt = catmull_rom_weights(t_ring, self.n_rings, periodic=False)
        dt_ds = 1.0 / np.maximum(np.gradient(self.ring_s)[np.clip(np.floor(t_ring).astype(int), 0,
                                                                    self.n_rings - 1)], 1e-9)
        wt, dwt_du = catmull_rom_weights(np.asarray(theta) / (2 * np.pi) * self.n_around, self.n_around, True)
        return SurfaceMap(ws, dws_dt * dt_ds[:, None], wt, dwt_du * self.n_around / (2 * np.pi))

    def material_points(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        """`count` (s, theta) material coordinates spread evenly over the unclamped wall by area: a
        golden-angle sequence, skipping the first 3 % of the length (inside the clamp)."""
        s_lo, s_hi = 0.03 * self.arc_length_mm, self.arc_length_mm
        # Inverse-CDF in s so that density per unit area is uniform (circumference ~ radius).
        grid = np.linspace(s_lo, s_hi, 512)
        r = np.interp(grid, self.ring_s, self.ring_r)
        cdf = np.concatenate([[0.0], np.cumsum(0.5 * (r[1:] + r[:-1]) * np.diff(grid))])
        cdf /= cdf[-1]
        q = (np.arange(count) + 0.5) / count
        s = np.interp(q, cdf, grid)
        theta = np.mod(np.arange(count) * np.pi * (3 - np.sqrt(5)), 2 * np.pi)
        return s, theta
