import numpy as np
import pytest
import torch

from vfdata.tracking.llr import llr_residual, nearest_neighbours, reconstruction_weights
from vfdata.tracking.sampling import farthest_point_sampling, isolated_points, select_reference_points


def test_neighbours_exclude_the_point_itself():
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 10, (200, 3))
    idx = nearest_neighbours(points, 6)
    assert idx.shape == (200, 6)
    assert not (idx == np.arange(200)[:, None]).any()
    d_own = np.linalg.norm(points[idx] - points[:, None], axis=2)
    assert (np.diff(d_own, axis=1) >= 0).all()
    with pytest.raises(ValueError):
        nearest_neighbours(points[:5], 5)


def test_weights_sum_to_one_and_reconstruct_points_on_a_curved_surface():
    rng = np.random.default_rng(1)
    uv = rng.uniform(-10, 10, (400, 2))
    points = np.column_stack([uv, 0.02 * uv[:, 0] ** 2 - 0.01 * uv[:, 1] ** 2])
    idx = nearest_neighbours(points, 8)
    w = reconstruction_weights(points, idx)
    assert np.allclose(w.sum(axis=1), 1.0)
    residual = points - np.einsum("nk,nkd->nd", w, points[idx])
    spacing = np.linalg.norm(points[idx[:, 0]] - points, axis=1).mean()
    assert np.median(np.linalg.norm(residual, axis=1)) < 0.05 * spacing


def test_weights_are_invariant_to_similarity_transforms_and_the_residual_sees_bending():
    rng = np.random.default_rng(2)
    points = np.column_stack([rng.uniform(-5, 5, (300, 2)), np.zeros(300)])
    idx = nearest_neighbours(points, 8)
    w = reconstruction_weights(points, idx)
    rotation = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    moved = 1.7 * points @ rotation.T + [3.0, -2.0, 40.0]
    assert np.allclose(reconstruction_weights(moved, idx), w, atol=1e-6)
    t_idx, t_w = torch.from_numpy(idx), torch.from_numpy(w)
    # The residual moves with the neighbourhood (regularised weights leave a small one at rest) ...
    rest = llr_residual(torch.from_numpy(points), t_idx, t_w).numpy()
    moved_residual = llr_residual(torch.from_numpy(moved), t_idx, t_w).numpy()
    assert np.allclose(moved_residual, 1.7 * rest @ rotation.T, atol=1e-9)
    # ... while bending changes it by far more than its rest value.
    bent = points.copy()
    bent[:, 2] = 0.3 * points[:, 0] ** 2
    change = np.linalg.norm(llr_residual(torch.from_numpy(bent), t_idx, t_w).numpy() - rest, axis=1)
    assert change.mean() > 0.05 > 3 * np.linalg.norm(rest, axis=1).mean()


def test_reconstruction_from_another_cloud():
    grid = np.stack(np.meshgrid(np.arange(10.0), np.arange(10.0)), axis=-1).reshape(-1, 2)
    basis = np.column_stack([grid, np.zeros(100)])
    query = np.array([[3.3, 4.6, 0.0], [7.5, 1.2, 0.0]])
    idx = np.argsort(np.linalg.norm(basis[None] - query[:, None], axis=2), axis=1)[:, :4]
    w = reconstruction_weights(query, idx, regularization=1e-8, basis=basis)
    assert np.allclose(np.einsum("nk,nkd->nd", w, basis[idx]), query, atol=1e-6)


def test_farthest_point_sampling_is_seeded_and_well_spread():
    rng = np.random.default_rng(3)
    points = rng.uniform(0, 100, (5000, 3))
    a = farthest_point_sampling(points, 64, seed=0)
    assert np.array_equal(a, farthest_point_sampling(points, 64, seed=0))
    assert not np.array_equal(a, farthest_point_sampling(points, 64, seed=1))
    assert len(np.unique(a)) == 64

    def min_spacing(idx):
        d = np.linalg.norm(points[idx][:, None] - points[idx][None], axis=2)
        return d[~np.eye(len(idx), dtype=bool)].min()

    random_pick = rng.choice(5000, 64, replace=False)
    assert min_spacing(a) > 3 * min_spacing(random_pick)
    assert len(farthest_point_sampling(points[:10], 64)) == 10


def test_reference_selection_leaves_out_flying_pixels():
    # A sheet sampled at ~0.5 mm plus one "flying pixel" 50 mm behind it, as colon_000's first frame has:
    # farthest-point sampling alone picks it (it is far from everything); the selection must not.
    rng = np.random.default_rng(0)
    sheet = np.c_[rng.uniform(-20, 20, (5000, 2)), np.full(5000, 80.0)]
    cloud = np.vstack([sheet, [[0.0, 0.0, 130.0]]])
    assert len(cloud) - 1 in farthest_point_sampling(cloud, 64, seed=0)
    assert np.flatnonzero(isolated_points(cloud)).tolist() == [len(cloud) - 1]
    chosen = select_reference_points(cloud, 64, seed=0)
    assert len(chosen) == 64 and len(cloud) - 1 not in chosen
    assert np.array_equal(chosen, select_reference_points(cloud, 64, seed=0))
    assert len(cloud) - 1 in select_reference_points(cloud, 64, seed=0, isolation_factor=0)  # 0 turns it off
