"""`--device cpu|cuda|auto`: CPU is the default and the tested path; `auto` on a machine without CUDA
runs there too, with the same results; asking for CUDA without one is a one-line error before any
work. On a machine with CUDA, the tracker and the force model on the GPU agree with the CPU."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from clip_fixtures import single_thread  # noqa: F401  (one torch thread per test)

from vfdata.cli import main
from vfdata.device import resolve_device, tracker_device_options
from vfdata.errors import VisionForceError
from vfdata.tracking import GeometryTracker
from vfdata.tracking.synthetic import DeformingSheet, press_and_stretch


@pytest.fixture
def no_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)




def test_devices_resolve_and_cuda_without_one_is_refused(no_cuda):
    assert resolve_device(None) == resolve_device("cpu") == resolve_device("auto") == "cpu"
    for name in ("cuda", "cuda:1"):
        with pytest.raises(VisionForceError, match=f"--device {name}: no CUDA device here"):
            resolve_device(name)
    with pytest.raises(VisionForceError, match="not one of cpu, cuda"):
        resolve_device("tpu")
    assert tracker_device_options("klt", "cpu") == {}  # the CPU changes no option (nor provenance)
    with pytest.raises(VisionForceError, match="'klt' tracker runs on the CPU only"):
        tracker_device_options("klt", "cuda")


@pytest.mark.parametrize("argv", [["process", "rec.mcap"], ["process", "--many", "a.mcap", "b.mcap"]])
def test_the_command_line_says_it_in_one_line(no_cuda, tmp_path, capsys, argv):
    assert main([*argv, "--device", "cuda"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--device cuda: no CUDA device here" in err[0]
    assert not list(tmp_path.iterdir())


def _track(device: str | None, frames: int = 4) -> np.ndarray:
    sheet = DeformingSheet(press_and_stretch(frames))
    options = {} if device is None else {"device": device}
    tracker = GeometryTracker(sheet.cloud(0, 3000), num_points=64, seed=0, **options)
    return np.stack([tracker.update(sheet.cloud(f, 3000))[0] for f in range(1, frames)])


def test_the_tracker_on_cpu_and_auto_without_cuda_are_the_default(no_cuda):
    default = _track(None)
    np.testing.assert_array_equal(_track("cpu"), default)
    np.testing.assert_array_equal(_track(resolve_device("auto")), default)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_the_tracker_and_force_model_on_cuda_agree_with_the_cpu():
    np.testing.assert_allclose(_track("cuda"), _track("cpu"), atol=0.05)  # mm; float32 on another device
    from test_predict import _regressor, _tracks

    from vfdata.clips.spec import ClipSpec
    from vfmodels import predict

    points, visible = _tracks(frames=20)
    reg = _regressor()
    cpu = predict.forces_from_tracks(reg, ClipSpec(), _as_tracks(points, visible), 8)[0]
    gpu = predict.forces_from_tracks(reg.to("cuda"), ClipSpec(), _as_tracks(points, visible), 8)[0]
    np.testing.assert_allclose(gpu, cpu, rtol=1e-3, atol=1e-4)


def _as_tracks(points, visible):
    from test_predict import _as_tracks as as_tracks

    return as_tracks(points, visible)
