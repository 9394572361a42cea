"""The image baselines: output shapes, and pretrained weights from a local file (or a clear error)."""

import pytest
import torch
from clip_fixtures import single_thread  # noqa: F401 - autouse fixture
from torchvision.models.video import r3d_18

from vfdata.errors import BackendError
from vfmodels import DepthViTLSTM, RGBResNet3D


def test_rgb_r3d_shapes_and_random_init():
    torch.manual_seed(0)
    model = RGBResNet3D().eval()
    assert model.initialisation == "random"
    images = torch.randint(0, 256, (2, 8, 3, 32, 32), dtype=torch.uint8)
    with torch.no_grad():
        out = model(images)
        assert out.shape == (2, 8, 3)
        # uint8 0-255 and float 0-1 inputs are the same image
        torch.testing.assert_close(out, model(images.float() / 255), atol=1e-5, rtol=1e-4)


def test_rgb_r3d_loads_local_weights(tmp_path):
    torch.manual_seed(1)
    source = r3d_18()
    torch.save({"state_dict": source.state_dict()}, tmp_path / "r3d.pth")
    model = RGBResNet3D(weights_path=str(tmp_path / "r3d.pth"))
    assert model.initialisation.startswith("pretrained:")
    torch.testing.assert_close(model.features[0][0].weight, source.stem[0].weight)
    with pytest.raises(BackendError, match="not found"):
        RGBResNet3D(weights_path=str(tmp_path / "missing.pth"))
    torch.save({"conv.weight": torch.zeros(3)}, tmp_path / "other.pth")
    with pytest.raises(BackendError, match="not r3d_18 weights"):
        RGBResNet3D(weights_path=str(tmp_path / "other.pth"))


@pytest.mark.slow  # two ViT-Small models (22 M parameters each) built and saved
def test_depth_vit_shapes_and_local_rgb_weights(tmp_path):
    import timm

    torch.manual_seed(0)
    model = DepthViTLSTM(img_size=32).eval()
    assert model.initialisation == "random"
    with torch.no_grad():
        assert model(torch.randn(2, 3, 1, 32, 32)).shape == (2, 3, 3)
    # RGB ImageNet-style ViT-S/16 weights at 224 px adapt to one channel and 32 px
    source = timm.create_model("vit_small_patch16_224", num_classes=1000)
    torch.save(source.state_dict(), tmp_path / "vit.pth")
    loaded = DepthViTLSTM(weights_path=str(tmp_path / "vit.pth"), img_size=32)
    assert loaded.vit.patch_embed.proj.weight.shape[1] == 1
    torch.testing.assert_close(loaded.vit.blocks[0].attn.qkv.weight, source.blocks[0].attn.qkv.weight)
    torch.save(r3d_18().state_dict(), tmp_path / "wrong.pth")
    with pytest.raises(BackendError, match="not ViT-Small"):
        DepthViTLSTM(weights_path=str(tmp_path / "wrong.pth"), img_size=32)


def test_depth_vit_is_causal():
    torch.manual_seed(0)
    model = DepthViTLSTM(img_size=32).eval()
    x = torch.randn(1, 4, 1, 32, 32)
    y = x.clone()
    y[:, 2:] = torch.randn_like(y[:, 2:])
    with torch.no_grad():
        torch.testing.assert_close(model(x)[:, :2], model(y)[:, :2])
