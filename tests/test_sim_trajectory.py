"""Grasper motion: starts at rest, stays within reach, moves at teleoperation speeds, releases."""

from __future__ import annotations

import numpy as np

from vfdata.sim.trajectory import JAW_OPEN_RAD, MotionLimits, plan_trajectory


def test_trajectory_is_like_teleoperation():
    limits = MotionLimits((-9.0, -30.0, -3.0), (27.0, 30.0, 9.0), tremor_mm=0.0)
    traj = plan_trajectory(np.random.default_rng(7), 120.0, limits)
    t = np.arange(0, 120.0, 1 / 120)
    disp, twist, jaw, holding = traj(t)
    assert np.allclose(disp[0], 0) and twist[0] == 0 and holding[0]
    assert (disp >= np.array(limits.lo_mm) - 1e-9).all() and (disp <= np.array(limits.hi_mm) + 1e-9).all()
    assert np.abs(twist).max() <= np.radians(limits.max_twist_deg) + 1e-9
    speed = np.linalg.norm(np.diff(disp, axis=0), axis=1) * 120
    # Minimum-jerk moves peak at 1.875 x their mean speed (at most 30 mm/s).
    assert speed.max() < 1.875 * 30 + 1
    assert (speed > 5).mean() > 0.2  # it moves most of the time ...
    assert (speed < 1e-6).mean() > 0.05  # ... and holds still sometimes
    # Every direction is exercised.
    assert disp[:, 0].max() > 0.5 * 27 and disp[:, 1].max() > 0.5 * 30 and disp[:, 1].min() < -0.5 * 30
    assert disp[:, 2].max() > 0.5 * 9
    # Releases: the jaws open fully, and the grasp point is back at rest when they close again.
    assert (~holding).any() and np.isclose(jaw.max(), JAW_OPEN_RAD)
    regrasp = np.nonzero(holding[1:] & ~holding[:-1])[0] + 1
    assert len(regrasp) and np.allclose(disp[regrasp], 0, atol=1e-2)


def test_trajectory_is_deterministic():
    limits = MotionLimits((-9.0, -30.0, -3.0), (27.0, 30.0, 9.0))
    t = np.linspace(0, 30, 500)
    a = plan_trajectory(np.random.default_rng(1), 30.0, limits)(t)
    b = plan_trajectory(np.random.default_rng(1), 30.0, limits)(t)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
