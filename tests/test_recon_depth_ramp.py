"""The first frame's depth gate follows a tissue that runs into depth (vfdata.recon.depth_ramp)."""

import numpy as np

from vfdata.recon.depth_ramp import ramp_gate


def tube_into_depth(h: int = 120, w: int = 80):
    """A box: a tube from the bottom (near, 100 mm) to the top (far, 190 mm) over a bed 30 mm behind its
    near end and farther up, as the simulator's colon at 270 degrees (the clamp 90 mm farther than the tip)."""
    v, u = np.mgrid[0:h, 0:w].astype(float)
    along = 1 - v / (h - 1)  # 0 at the near end (bottom), 1 at the far end (top)
    centre = 0.3 * w + 0.4 * w * along  # the tube leans across the box
    across = np.abs(u - centre) / 12.0
    tube = across < 1
    tube_depth = 100 + 90 * along + 8 * across**2  # the rims a little farther than the top
    bed_depth = 130 + 150 * along
    depth = np.where(tube, tube_depth, bed_depth)
    return depth, tube


def test_the_gate_follows_the_ramp_to_the_far_end_and_leaves_the_bed_beside_the_near_end():
    depth, tube = tube_into_depth()
    h, w = depth.shape
    seed = np.zeros_like(tube)
    seed[h * 2 // 5 : h * 3 // 5, w * 2 // 5 : w * 3 // 5] = True
    seed &= tube
    gate = ramp_gate(depth, np.ones_like(tube), seed, tolerance_mm=18.0)
    assert gate[tube].mean() > 0.97  # the far (clamped) half included
    assert gate[~tube].mean() < 0.05  # the bed stays out
    # A constant band around the middle's depth, what the gate replaces, loses the far half and takes bed.
    band = np.abs(depth - np.median(depth[seed])) <= 18.0
    assert band[tube].mean() < 0.6 and band[~tube].sum() > 100


def test_pixels_not_usable_and_pixels_cut_off_from_the_seed_stay_out():
    depth, tube = tube_into_depth()
    h, w = depth.shape
    seed = np.zeros_like(tube)
    seed[h // 2 - 3 : h // 2 + 3] = True
    seed &= tube
    usable = np.ones_like(tube)
    usable[10:14] = False  # an instrument across the tube near its far end
    island = np.zeros_like(tube)
    island[2:6, 2:6] = True  # bed pixels at the depth the tube has in their rows, not connected to it
    depth = np.where(island, 189.0, depth)
    gate = ramp_gate(depth, usable, seed, tolerance_mm=18.0)
    assert not gate[~usable].any()
    assert not gate[island].any()
    assert gate[tube & (np.arange(h)[:, None] > 14)].mean() > 0.97


def test_an_instrument_across_the_tube_bridges_its_two_halves_but_is_never_taken():
    depth, tube = tube_into_depth()
    h, w = depth.shape
    rows = np.arange(h)[:, None]
    seed = np.zeros_like(tube)
    seed[h // 2 - 3 : h // 2 + 3] = True
    seed &= tube
    metal = np.zeros_like(tube)
    metal[20:30] = True  # a shaft across the whole box, in front of the tube's far part
    usable = ~metal
    far = tube & (rows < 20)
    # Without the bridge the far part, cut off from the seed by the shaft, is lost (the fresh colon view
    # at 293 degrees: first-frame mask IoU 0.75); through it, it is kept.
    assert ramp_gate(depth, usable, seed, tolerance_mm=18.0)[far].mean() < 0.05
    gate = ramp_gate(depth, usable, seed, tolerance_mm=18.0, bridge=metal)
    assert gate[far].mean() > 0.95 and gate[tube & (rows >= 30)].mean() > 0.97
    assert not gate[metal].any() and gate[~tube & ~metal].mean() < 0.05  # the bed beside it stays out
