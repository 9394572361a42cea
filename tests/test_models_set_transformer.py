"""SetTransformerLSTM: shapes, invariance to point order, masking, causality."""

import pytest
import torch
import torch.nn.functional as F
from clip_fixtures import single_thread  # noqa: F401 - autouse fixture

from vfmodels.networks.set_transformer import InducedSetAttentionBlock, MultiheadAttentionBlock, SetTransformerLSTM


@pytest.fixture
def model() -> SetTransformerLSTM:
    torch.manual_seed(0)
    return SetTransformerLSTM(in_features=6).eval()


def clip(b=2, t=8, n=40, c=6, seed=1):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(b, t, n, c, generator=g), torch.rand(b, t, n, generator=g) > 0.3


def test_shapes(model):
    x, valid = clip()
    assert model(x, valid).shape == (2, 8, 3)
    assert model(x).shape == (2, 8, 3)
    assert model(x[:, :, :7], valid[:, :, :7]).shape == (2, 8, 3)
    assert model.encode_frames(x, valid).shape == (2, 8, 64)


def test_invariant_to_point_order(model):
    x, valid = clip()
    perm = torch.randperm(x.shape[2], generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        a, b = model(x, valid), model(x[:, :, perm], valid[:, :, perm])
    torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    # and the set blocks themselves are equivariant
    isab = InducedSetAttentionBlock(16, 4, 5)
    y = torch.randn(3, 20, 16)
    p = torch.randperm(20)
    torch.testing.assert_close(isab(y)[:, p], isab(y[:, p]), atol=1e-5, rtol=1e-5)


def test_order_matters_across_frames(model):
    # Sanity check that the test above can fail: reordering frames (not points) changes the output.
    x, valid = clip()
    with torch.no_grad():
        assert not torch.allclose(model(x, valid), model(x.flip(1), valid.flip(1)), atol=1e-4)


def test_invalid_points_are_ignored(model):
    x, valid = clip()
    y = x.clone()
    y[~valid] = torch.nan  # whatever an invisible point carries must not matter
    z = x.clone()
    z[~valid] = 1e6
    with torch.no_grad():
        torch.testing.assert_close(model(x, valid), model(y, valid))
        torch.testing.assert_close(model(x, valid), model(z, valid))
        # dropping the invalid points altogether gives the same per-frame embedding
        keep = valid[0, 0]
        full = model.encode_frames(x[:1, :1], valid[:1, :1])
        dropped = model.encode_frames(x[:1, :1, keep], None)
    torch.testing.assert_close(full, dropped, atol=1e-5, rtol=1e-5)


def test_frame_without_visible_points_is_finite(model):
    x, valid = clip()
    valid[0, 3] = False
    with torch.no_grad():
        assert torch.isfinite(model(x, valid)).all()


def test_causal_in_time(model):
    x, valid = clip(t=12)
    x2 = x.clone()
    x2[:, 7:] = torch.randn_like(x2[:, 7:])
    with torch.no_grad():
        a, b = model(x, valid), model(x2, valid)
    torch.testing.assert_close(a[:, :7], b[:, :7])
    assert (a[:, 7:] - b[:, 7:]).abs().max() > 1e-4
    # and by gradients: the output at frame 4 has zero gradient with respect to frames 5..11
    xg = x.clone().requires_grad_(True)
    model(xg, valid)[:, 4].sum().backward()
    assert xg.grad[:, 5:].abs().max() == 0
    assert xg.grad[:, :5].abs().max() > 0


def test_mab_masks_keys():
    torch.manual_seed(0)
    mab = MultiheadAttentionBlock(8, 2)
    q, k = torch.randn(1, 3, 8), torch.randn(1, 5, 8)
    valid = torch.tensor([[True, True, False, True, False]])
    torch.testing.assert_close(mab(q, k, valid), mab(q, k[:, valid[0]]), atol=1e-6, rtol=1e-5)


def test_rejects_bad_head_count():
    with pytest.raises(ValueError):
        SetTransformerLSTM(dim=64, heads=5)


def test_few_keys_attention_matches_per_head_attention():
    # The compiled path's block-diagonal arithmetic must be the same attention as the per-head kernel.
    torch.manual_seed(0)
    mab = MultiheadAttentionBlock(64, 4)
    q, k, v = torch.randn(3, 256, 64), torch.randn(3, 16, 64), torch.randn(3, 16, 64)
    expected = F.scaled_dot_product_attention(mab._split(q), mab._split(k), mab._split(v))
    expected = expected.transpose(1, 2).reshape(3, 256, 64)
    torch.testing.assert_close(mab._attend_few_keys(q, k, v), expected, atol=1e-5, rtol=1e-5)


@pytest.mark.slow
def test_compiled_model_matches_eager():
    torch.manual_seed(0)
    model = SetTransformerLSTM(in_features=6).eval()
    x, valid = torch.randn(2, 4, 64, 6), torch.rand(2, 4, 64) > 0.2
    with torch.inference_mode():
        torch.testing.assert_close(torch.compile(model)(x, valid), model(x, valid), atol=1e-6, rtol=1e-5)
