"""Third-party network weights load as tensors only: a checkpoint that pickles code is refused by
every loader (Stereo Any Video, SAM2, the tissue detector, CoTracker) before any of it runs."""

from __future__ import annotations

import os

import pytest

torch = pytest.importorskip("torch")

from vfdata.errors import InputError  # noqa: E402
from vfdata.recon import DetectorPrompt, make_depth_estimator, make_segmenter  # noqa: E402
from vfdata.tracking import load_cotracker  # noqa: E402
from vfdata.weights import load_state_dict, load_weights  # noqa: E402


class _MakesADirectory:
    """Unpickling this calls os.makedirs(path): the harmless stand-in for `os.system(...)`."""

    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return (os.makedirs, (self.path,))


@pytest.fixture
def code_checkpoint(tmp_path):
    """A checkpoint whose state dict sits beside a pickled call, and the folder the call would make."""
    marker = tmp_path / "the-checkpoint-ran-code"
    path = tmp_path / "weights.pth"
    torch.save({"model": {"weight": torch.zeros(2)}, "extra": _MakesADirectory(str(marker))}, path)
    return path, marker


def test_tensors_load(tmp_path):
    torch.save({"model": {"weight": torch.arange(3.0)}}, tmp_path / "ok.pth")
    state = load_weights(tmp_path / "ok.pth", "test checkpoint")
    assert torch.equal(state["model"]["weight"], torch.arange(3.0))


@pytest.mark.parametrize("saved", [{"weight": torch.arange(3.0)}, {"model": {"weight": torch.arange(3.0)}},
                                   {"state_dict": {"module.weight": torch.arange(3.0)}}, {"epoch": 3}])
def test_state_dict_unwrapped(tmp_path, saved):
    torch.save(saved, tmp_path / "ok.pth")
    state = load_state_dict(tmp_path / "ok.pth", "test checkpoint")
    assert state == {"epoch": 3} if "epoch" in saved else torch.equal(state["weight"], torch.arange(3.0))


def test_not_a_state_dict_is_named(tmp_path):
    torch.save({"model": [torch.zeros(1)]}, tmp_path / "list.pth")
    with pytest.raises(InputError, match="list.pth: a test checkpoint holds a state dict, not a list"):
        load_state_dict(tmp_path / "list.pth", "test checkpoint")
    with pytest.raises(InputError, match="a detector weights file holds a state dict, not a list"):
        DetectorPrompt(weights=tmp_path / "list.pth")


def test_pickled_code_is_refused_without_running(code_checkpoint):
    path, marker = code_checkpoint
    with pytest.raises(InputError, match="holds pickled code \\(os.makedirs\\)") as caught:
        load_weights(path, "test checkpoint")
    assert caught.value.path == path and str(path) in str(caught.value)
    assert not marker.exists()


def test_a_whole_pickled_model_is_refused(tmp_path):
    torch.save(torch.nn.Linear(2, 2), tmp_path / "model.pth")  # a module, not its state dict
    with pytest.raises(InputError, match="pickled code .*Linear"):
        load_weights(tmp_path / "model.pth", "test checkpoint")


@pytest.mark.parametrize("content", [b"", b"not a checkpoint", b"PK\x03\x04 truncated zip"])
def test_damaged_files_are_named(tmp_path, content):
    (tmp_path / "bad.pth").write_bytes(content)
    with pytest.raises(InputError, match="bad.pth: not a readable test checkpoint"):
        load_weights(tmp_path / "bad.pth", "test checkpoint")


def test_every_loader_refuses_pickled_code(tmp_path, code_checkpoint):
    path, marker = code_checkpoint
    with pytest.raises(InputError, match="detector weights file holds pickled code"):
        DetectorPrompt(weights=path)
    # The checkout's model code is never imported: the checkpoint is refused first.
    checkout = tmp_path / "stereoanyvideo"
    (checkout / "models" / "core").mkdir(parents=True)
    (checkout / "models" / "core" / "stereoanyvideo.py").write_text("raise SystemExit('imported')\n")
    with pytest.raises(InputError, match="Stereo Any Video checkpoint holds pickled code"):
        make_depth_estimator("stereoanyvideo", code=checkout, checkpoint=path, device="cpu")
    with pytest.raises(InputError, match="SAM2 checkpoint holds pickled code"):
        make_segmenter("sam2", config="configs/sam2.1/sam2.1_hiera_l.yaml", checkpoint=path, device="cpu")
    with pytest.raises(InputError, match="CoTracker3 checkpoint holds pickled code"):
        load_cotracker(path)
    assert not marker.exists()
