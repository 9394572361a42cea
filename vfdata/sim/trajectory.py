"""Grasper motion like teleoperation: a random sequence of minimum-jerk moves (stretch, lift, lateral
pulls, combined pulls, twists, returns), holds, and releases with re-grasps, plus a small tremor.

Displacements are of the grasp point from its rest position, in the object frame (mm); the twist is a
rotation of the jaws about the tube axis (rad).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Moves are drawn without replacement from this bag (refilled when empty) so that every recording
# exercises every direction: lateral pulls alternate sides, combined pulls come twice per round.
_MOVE_BAG = ("stretch", "lift", "lateral", "lateral", "combined", "combined", "twist", "return")
JAW_OPEN_RAD = np.radians(30.0)


@dataclass(frozen=True)
class MotionLimits:
    """Reach of the grasp point (mm, object frame: X up, Y lateral, Z along the tube) and speeds."""

    lo_mm: tuple[float, float, float]
    hi_mm: tuple[float, float, float]
    max_twist_deg: float = 25.0
    speed_mm_s: tuple[float, float] = (5.0, 30.0)
    tremor_mm: float = 0.12


@dataclass(frozen=True)
class Segment:
    t0: float
    t1: float
    p0: np.ndarray
    p1: np.ndarray
    twist0: float
    twist1: float
    jaw0: float  # jaw opening (rad) at t0 and t1; 0 = closed on the tissue
    jaw1: float
    kind: str


def _min_jerk(tau: np.ndarray) -> np.ndarray:
    tau = np.clip(tau, 0.0, 1.0)
    return tau**3 * (10 - 15 * tau + 6 * tau**2)


class GraspTrajectory:
    """A piecewise minimum-jerk grasper motion. Call with times (s) to get displacement (T, 3) mm,
    twist (T,) rad, jaw opening (T,) rad and whether the jaws hold the tissue (T,) bool."""

    def __init__(self, segments: list[Segment], tremor: tuple[np.ndarray, np.ndarray, np.ndarray]):
        self.segments = segments
        self._starts = np.array([s.t0 for s in segments])
        self._tremor_amp, self._tremor_freq, self._tremor_phase = tremor

    @property
    def duration_s(self) -> float:
        return self.segments[-1].t1

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        k = np.clip(np.searchsorted(self._starts, t, side="right") - 1, 0, len(self.segments) - 1)
        t0 = self._starts[k]
        t1 = np.array([self.segments[i].t1 for i in k])
        s = _min_jerk((t - t0) / np.maximum(t1 - t0, 1e-9))
        p0 = np.stack([self.segments[i].p0 for i in k])
        p1 = np.stack([self.segments[i].p1 for i in k])
        disp = p0 + (p1 - p0) * s[:, None]
        tw = np.array([self.segments[i].twist0 for i in k])
        tw = tw + (np.array([self.segments[i].twist1 for i in k]) - tw) * s
        jaw0 = np.array([self.segments[i].jaw0 for i in k])
        jaw = jaw0 + (np.array([self.segments[i].jaw1 for i in k]) - jaw0) * s
        # Physiological tremor, scaled down by the master-slave motion scaling.
        phase = 2 * np.pi * self._tremor_freq[None, :, :] * t[:, None, None] + self._tremor_phase[None]
        ramp = np.clip(t / 0.5, 0.0, 1.0)[:, None]  # starts exactly at rest
        disp = disp + ramp * (self._tremor_amp[None] * np.sin(phase)).sum(axis=2)
        holding = jaw <= 1e-9
        return disp, tw, jaw, holding


def plan_trajectory(rng: np.random.Generator, duration_s: float, limits: MotionLimits) -> GraspTrajectory:
    """A random grasper motion of at least `duration_s`: starts holding the tissue at rest for 0.5 s."""
    lo, hi = np.asarray(limits.lo_mm, float), np.asarray(limits.hi_mm, float)
    max_twist = np.radians(limits.max_twist_deg)
    segments: list[Segment] = []
    t, p, twist = 0.0, np.zeros(3), 0.0
    since_release = 0.0
    bag: list[str] = []
    lateral_side = 1.0 if rng.random() < 0.5 else -1.0

    def add(duration: float, p1: np.ndarray, twist1: float, jaw0: float, jaw1: float, kind: str) -> None:
        nonlocal t, p, twist
        segments.append(Segment(t, t + duration, p.copy(), p1.copy(), twist, twist1, jaw0, jaw1, kind))
        t, p, twist = t + duration, p1.copy(), twist1

    def move_time(p1: np.ndarray, twist1: float) -> float:
        speed = rng.uniform(*limits.speed_mm_s)
        # A twist moves the jaw tips by about 8 mm per radian.
        dist = np.linalg.norm(p1 - p) + 8.0 * abs(twist1 - twist)
        return max(dist / speed, 0.4)

    add(0.5, p, 0.0, 0.0, 0.0, "hold")
    while t < duration_s:
        r = rng.random()
        if since_release > 8.0 and r < 0.12:
            # Release: open, go back to rest with open jaws, wait, close on the tissue again.
            add(0.35, p, twist, 0.0, JAW_OPEN_RAD, "open")
            add(move_time(np.zeros(3), 0.0), np.zeros(3), 0.0, JAW_OPEN_RAD, JAW_OPEN_RAD, "release")
            add(rng.uniform(0.4, 1.2), np.zeros(3), 0.0, JAW_OPEN_RAD, JAW_OPEN_RAD, "wait")
            add(0.35, np.zeros(3), 0.0, JAW_OPEN_RAD, 0.0, "close")
            since_release = 0.0
            continue
        if r < 0.3:
            dur = rng.uniform(0.3, 2.0)
            add(dur, p, twist, 0.0, 0.0, "hold")
            since_release += dur
            continue
        if not bag:
            bag = [_MOVE_BAG[i] for i in rng.permutation(len(_MOVE_BAG))]
        kind = bag.pop()
        target = p * rng.uniform(0.0, 0.5)
        twist1 = twist * rng.uniform(0.0, 0.6)
        if kind == "stretch":
            target[2] = hi[2] * rng.uniform(0.5, 1.0)
        elif kind == "lift":
            target[0] = hi[0] * rng.uniform(0.5, 1.0) if rng.random() < 0.75 else lo[0] * rng.uniform(0.5, 1)
        elif kind == "lateral":
            target[1] = (hi[1] if lateral_side > 0 else lo[1]) * rng.uniform(0.6, 1.0)
            lateral_side = -lateral_side
        elif kind == "combined":
            # Inside the ellipsoid through the reach limits: the box corners would stretch the
            # tissue far past what a surgeon would ask of it.
            target = rng.uniform(lo, hi)
            scale = np.sqrt(np.sum((target / np.where(target >= 0, hi, -lo)) ** 2))
            target = target / max(1.0, scale)
        elif kind == "twist":
            twist1 = rng.uniform(-max_twist, max_twist)
        else:  # return
            target, twist1 = np.zeros(3), 0.0
        if kind in ("stretch", "lift", "lateral", "combined") and rng.random() < 0.25:
            twist1 = rng.uniform(-max_twist, max_twist) * 0.5
        target = np.clip(target, lo, hi)
        dur = move_time(target, twist1)
        add(dur, target, twist1, 0.0, 0.0, kind)
        since_release += dur
    tremor_amp = np.full((3, 3), limits.tremor_mm / np.sqrt(3)) * rng.uniform(0.5, 1.0, (3, 3))
    tremor_freq = rng.uniform(2.0, 9.0, (3, 3))
    tremor_phase = rng.uniform(0, 2 * np.pi, (3, 3))
    return GraspTrajectory(segments, (tremor_amp, tremor_freq, tremor_phase))
