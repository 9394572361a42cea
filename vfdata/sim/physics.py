"""Deformable tube: a damped, strain-stiffening, viscoelastic mass-spring network, integrated with
linearised backward Euler (one Newton step per time step, as in Baraff & Witkin 1998).

Each spring carries a tension (N) made of three parallel branches, with strain e = (l - L0) / L0:
- elastic, stiffening in tension and soft in compression (a thin wall buckles):
  k (e + beta e^3) for e >= 0, k * compression_ratio * e for e < 0;
- a Kelvin-Voigt dashpot c de/dt, c = k * kelvin_voigt_s (the rate-dependent part);
- a Maxwell branch k_m (e - q) whose internal strain q relaxes toward e with time constant tau
  (stress relaxation while the grasper holds still).
Here k = E * wall * tributary width * kind factor, so spring stiffness follows the membrane modulus.

Units: positions mm, velocities mm/s, forces N, masses kg, time s. Nodes of ring 0 are clamped to
the fixture; the grasper drives a set of nodes kinematically. The force sensor reads what the tissue
pushes on the clamp (the clamp reaction reversed) in the sensor frame, whose axes are the object
frame's and whose origin lies `sensor_offset_mm` behind the clamp along -Z.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.linalg import solveh_banded

from vfdata.sim.tissue import SPRING_KINDS, Tube

GRAVITY_M_S2 = 9.81
UP = np.array([1.0, 0.0, 0.0])  # object-frame X is up


@dataclass(frozen=True)
class Material:
    """Mechanical parameters of the tube wall (see the module docstring for the model)."""

    modulus_mpa: float = 0.35
    wall_mm: float = 1.5
    density_kg_m3: float = 1050.0
    stiffening: float = 6.0
    compression_ratio: float = 0.25
    kelvin_voigt_s: float = 0.04
    maxwell_ratio: float = 0.3
    maxwell_tau_s: float = 1.5
    air_damping_per_s: float = 20.0
    # Relative stiffness of each spring kind, in the order of tissue.SPRING_KINDS.
    kind_factors: tuple[float, ...] = (1.0, 1.0, 0.35, 0.25, 0.25, 0.15)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["kind_factors"] = dict(zip(SPRING_KINDS, self.kind_factors, strict=True))
        return d


@dataclass
class Wrench:
    force_n: np.ndarray   # (3,)
    torque_nm: np.ndarray  # (3,)


@dataclass
class TubeModel:
    """Simulation state and stepping. `grasp(nodes, targets)` fixes nodes to given positions for the
    next step; `release()` frees them."""

    tube: Tube
    material: Material
    sensor_offset_mm: float = 20.0
    x: np.ndarray = field(init=False)
    v: np.ndarray = field(init=False)
    q: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        tube, mat = self.tube, self.material
        self.i, self.j, kind = tube.springs
        rest = tube.rest_nodes.reshape(-1, 3)
        self.rest_length = np.linalg.norm(rest[self.j] - rest[self.i], axis=1)
        factors = np.asarray(mat.kind_factors)[kind]
        self.k = mat.modulus_mpa * mat.wall_mm * tube.spring_tributary_mm * factors  # N per unit strain
        self.c = self.k * mat.kelvin_voigt_s
        self.k_m = self.k * mat.maxwell_ratio
        self.mass = tube.node_mass_kg
        self.n = tube.n_nodes
        self.clamped = np.arange(tube.n_around)  # ring 0
        self.gravity_n = -self.mass[:, None] * GRAVITY_M_S2 * UP[None, :]
        self.sensor_origin = np.array([0.0, 0.0, -self.sensor_offset_mm])
        is_clamped = np.zeros(self.n, bool)
        is_clamped[self.clamped] = True
        self._clamp_springs = np.nonzero(is_clamped[self.i] | is_clamped[self.j])[0]
        self._grasped = np.zeros(0, dtype=np.int64)
        self._targets = np.zeros((0, 3))
        self._build_band_index()
        self.x = rest.copy()
        self.v = np.zeros_like(self.x)
        self.q = np.zeros(len(self.k))

    # --- assembly ---------------------------------------------------------------------------------

    def _build_band_index(self) -> None:
        """Index arrays placing the upper-triangle entries of each spring's four 3x3 blocks into
        upper banded storage."""
        ndof = 3 * self.n
        self.bandwidth = int(3 * np.max(np.abs(self.j - self.i)) + 2)
        a, b = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
        rows, cols, entry, sign = [], [], [], []
        for p, q_, sgn in ((self.i, self.i, 1.0), (self.j, self.j, 1.0), (self.i, self.j, -1.0),
                           (self.j, self.i, -1.0)):
            r = (3 * p[:, None, None] + a[None]).reshape(len(p), 9)
            c = (3 * q_[:, None, None] + b[None]).reshape(len(p), 9)
            e = np.arange(len(p))[:, None] * 9 + np.arange(9)[None, :]
            keep = r <= c
            rows.append(r[keep])
            cols.append(c[keep])
            entry.append(e[keep])
            sign.append(np.full(int(keep.sum()), sgn))
        self._rows = np.concatenate(rows)
        self._cols = np.concatenate(cols)
        self._entry = np.concatenate(entry)  # index into the flattened (S, 3, 3) blocks
        self._sign = np.concatenate(sign)
        self._flat = (self.bandwidth + self._rows - self._cols) * ndof + self._cols

    def _spring_terms(self, x: np.ndarray, v: np.ndarray, sel: np.ndarray | slice = slice(None)
                      ) -> dict[str, np.ndarray]:
        """Directions, strains and tensions of the springs `sel` at positions x, velocities v."""
        i, j, rest = self.i[sel], self.j[sel], self.rest_length[sel]
        k, k_m = self.k[sel], self.k_m[sel]
        dx = x[j] - x[i]
        length = np.sqrt(np.einsum("sx,sx->s", dx, dx))
        d = dx / np.maximum(length, 1e-9)[:, None]
        e = (length - rest) / rest
        e_dot = np.einsum("sx,sx->s", d, v[j] - v[i]) / rest
        mat = self.material
        tension_side = e >= 0
        t_el = np.where(tension_side, k * (e + mat.stiffening * e**3), k * mat.compression_ratio * e)
        kt_el = np.where(tension_side, k * (1 + 3 * mat.stiffening * e**2), k * mat.compression_ratio)
        t_m = k_m * (e - self.q[sel])
        return {"d": d, "length": length, "e": e, "t_static": t_el + t_m, "kt": kt_el + k_m,
                "t_visc": self.c[sel] * e_dot}

    def _node_forces(self, tension: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Spring tensions -> (n, 3) forces on the nodes (a tense spring pulls its ends together)."""
        f = tension[:, None] * d
        out = np.zeros((self.n, 3))
        for axis in range(3):
            out[:, axis] = (np.bincount(self.i, f[:, axis], minlength=self.n)
                            - np.bincount(self.j, f[:, axis], minlength=self.n))
        return out

    def _banded(self, coef_dd: np.ndarray, coef_perp: np.ndarray, diag: np.ndarray,
                constrained: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Upper banded matrix of sum_s (coef_perp I + (coef_dd - coef_perp) d d^T) over the graph
        Laplacian pattern, plus diag; rows and columns of constrained dofs replaced by identity.
        Also returns the (S, 3, 3) spring blocks (for matrix-vector products)."""
        ndof = 3 * self.n
        block = coef_perp[:, None, None] * np.eye(3) + (coef_dd - coef_perp)[:, None, None] * (
            d[:, :, None] * d[:, None, :])
        vals = block.reshape(-1)[self._entry] * self._sign
        keep = ~constrained[self._rows] & ~constrained[self._cols]
        ab = np.bincount(self._flat[keep], vals[keep], minlength=(self.bandwidth + 1) * ndof)
        ab = ab.reshape(self.bandwidth + 1, ndof)
        ab[self.bandwidth] += np.where(constrained, 0.0, diag)
        ab[self.bandwidth, constrained] = 1.0
        return ab, block

    def _matvec(self, block: np.ndarray, diag: np.ndarray, vec: np.ndarray) -> np.ndarray:
        """Full (unconstrained) matrix times vec (3n,), the matrix being the spring blocks + diag."""
        w = vec.reshape(self.n, 3)
        f = np.einsum("sab,sb->sa", block, w[self.i] - w[self.j])
        y = np.zeros((self.n, 3))
        for axis in range(3):
            y[:, axis] = (np.bincount(self.i, f[:, axis], minlength=self.n)
                          - np.bincount(self.j, f[:, axis], minlength=self.n))
        return y.ravel() + diag * vec

    # --- constraints -------------------------------------------------------------------------------

    def grasp(self, nodes: np.ndarray, targets_mm: np.ndarray) -> None:
        """Drive `nodes` to `targets_mm` (k, 3) at the end of the next step."""
        self._grasped = np.asarray(nodes, dtype=np.int64)
        self._targets = np.asarray(targets_mm, dtype=np.float64).reshape(-1, 3)

    def release(self) -> None:
        self.grasp(np.zeros(0, dtype=np.int64), np.zeros((0, 3)))

    @property
    def grasped(self) -> np.ndarray:
        return self._grasped

    def _constraint_targets(self) -> tuple[np.ndarray, np.ndarray]:
        nodes = np.concatenate([self.clamped, self._grasped])
        targets = np.concatenate([self.tube.rest_nodes.reshape(-1, 3)[self.clamped], self._targets])
        return nodes, targets

    # --- stepping ----------------------------------------------------------------------------------

    def step(self, h: float) -> None:
        """Advance by h seconds (linearised backward Euler; constrained nodes reach their targets)."""
        nodes, targets = self._constraint_targets()
        constrained = np.zeros(3 * self.n, dtype=bool)
        constrained[(3 * nodes[:, None] + np.arange(3)).ravel()] = True
        w_c = np.zeros((self.n, 3))
        w_c[nodes] = (targets - self.x[nodes]) / h

        terms = self._spring_terms(self.x, self.v)
        d, length = terms["d"], terms["length"]
        mass_mm = np.repeat(self.mass * 1e-3, 3)  # N s^2 / mm
        diag = mass_mm * (1.0 + h * self.material.air_damping_per_s)
        geometric = np.maximum(terms["t_static"] / length, 0.0)
        coef_dd = h * self.c / self.rest_length + h * h * terms["kt"] / self.rest_length
        coef_perp = h * h * geometric
        ab, vals = self._banded(coef_dd, coef_perp, diag, constrained, d)

        f = self._node_forces(terms["t_static"], d) + self.gravity_n
        rhs = (mass_mm * self.v.ravel()) + h * f.ravel()
        rhs -= self._matvec(vals, diag, w_c.ravel())  # move the prescribed velocities to the right
        rhs[constrained] = w_c.ravel()[constrained]
        w = solveh_banded(ab, rhs, lower=False, check_finite=False).reshape(self.n, 3)
        w[nodes] = w_c[nodes]
        self.x = self.x + h * w
        self.x[nodes] = targets
        self.v = w
        e_new = (np.linalg.norm(self.x[self.j] - self.x[self.i], axis=1) - self.rest_length) / self.rest_length
        decay = np.exp(-h / self.material.maxwell_tau_s)
        self.q = e_new + (self.q - e_new) * decay

    def relax(self, tol_n: float = 1e-9, max_iter: int = 200) -> float:
        """Static equilibrium under gravity and the current constraints, fully relaxed (Maxwell branch
        unloaded, velocities zero), by Newton iterations. Returns the final residual force (N)."""
        nodes, targets = self._constraint_targets()
        self.x[nodes] = targets
        constrained = np.zeros(3 * self.n, dtype=bool)
        constrained[(3 * nodes[:, None] + np.arange(3)).ravel()] = True
        self.v[:] = 0.0
        residual = np.inf
        for _ in range(max_iter):
            self.q = (np.linalg.norm(self.x[self.j] - self.x[self.i], axis=1)
                      - self.rest_length) / self.rest_length
            terms = self._spring_terms(self.x, self.v)
            f = (self._node_forces(terms["t_static"], terms["d"]) + self.gravity_n).ravel()
            f[constrained] = 0.0
            residual = float(np.abs(f).max())
            if residual < tol_n:
                break
            coef_dd = terms["kt"] / self.rest_length
            coef_perp = np.maximum(terms["t_static"] / terms["length"], 0.0)
            # A little regularisation keeps directions without stiffness (a slack wall) solvable.
            ab, _ = self._banded(coef_dd, coef_perp, np.full(3 * self.n, 1e-3), constrained, terms["d"])
            dx = solveh_banded(ab, f, lower=False, check_finite=False).reshape(self.n, 3)
            step = np.abs(dx).max()
            if step > 2.0:  # damp large Newton steps
                dx *= 2.0 / step
            self.x = self.x + dx
        self.q = (np.linalg.norm(self.x[self.j] - self.x[self.i], axis=1) - self.rest_length) / self.rest_length
        return residual

    # --- read-outs ---------------------------------------------------------------------------------

    def spring_node_forces(self) -> np.ndarray:
        """(n, 3) forces the springs (elastic, Maxwell and viscous) exert on each node (N)."""
        terms = self._spring_terms(self.x, self.v)
        return self._node_forces(terms["t_static"] + terms["t_visc"], terms["d"])

    def sensor_wrench(self) -> Wrench:
        """What the tissue exerts on the clamp, in the sensor frame: force (N) and torque (N m) about
        the sensor origin. Includes the tissue's weight (the sensor is not tared here)."""
        sel = self._clamp_springs
        terms = self._spring_terms(self.x, self.v, sel)
        f = (terms["t_static"] + terms["t_visc"])[:, None] * terms["d"]
        on_node = np.zeros((self.n, 3))
        np.add.at(on_node, self.i[sel], f)
        np.add.at(on_node, self.j[sel], -f)
        load = on_node[self.clamped] + self.gravity_n[self.clamped]
        arm_m = (self.x[self.clamped] - self.sensor_origin) * 1e-3
        return Wrench(load.sum(0), np.cross(arm_m, load).sum(0))

    def grasp_force(self) -> np.ndarray:
        """(3,) force the grasper exerts on the tissue (N), from the balance of the grasped nodes
        (their inertia is negligible)."""
        if len(self._grasped) == 0:
            return np.zeros(3)
        f = self.spring_node_forces()[self._grasped] + self.gravity_n[self._grasped]
        return -f.sum(0)

    @property
    def nodes(self) -> np.ndarray:
        """(n_rings, n_around, 3) current node positions (mm, object frame)."""
        return self.x.reshape(self.tube.n_rings, self.tube.n_around, 3)

    @property
    def total_mass_kg(self) -> float:
        return float(self.mass.sum())
