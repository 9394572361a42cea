"""Where the torch work runs: `--device cpu|cuda|auto` (the tracker's SIREN fit and nearest
neighbours, the force model, the image baselines; training through Lightning's accelerator).

CPU is the default and the tested path. `cuda` (or `cuda:N`) puts every part that has a GPU path
there; asking for it on a machine without one is one line naming the option, before any work. `auto`
puts each kind of work (`WORK`) where it measured faster on a machine with CUDA (docs/gpu.md): the
training on the GPU, the per-frame work of `process`, `predict` and `live` on the CPU, so `auto` is
never slower than `cpu` there, by construction."""

from __future__ import annotations

from vfdata.errors import VisionForceError
from vfdata.tracker_kinds import GPU_TRACKERS

DEVICES = ("cpu", "cuda", "auto")
DEVICE_HELP = ("where the tracker's SIREN fit and nearest neighbours and the force model run: cpu (default), "
               "cuda (cuda:N), or auto (training on CUDA when present; the per-frame work, measured faster on "
               "the CPU, stays there: docs/gpu.md)")

# What `--device auto` picks on a machine with CUDA, per kind of work. Measured on one H200 against one
# thread of the same machine's CPU (docs/gpu.md):
# - "frames": one frame at a time, the geometry tracker in `process`, `predict` and `live`, and the force
#   model of a stream (batch 1). The tracker alone ran 128 frames/s on the GPU against 99 on the CPU, but
#   the stream with tracker and model on the GPU was slower than on the CPU (34.7 against 45.2 frames/s
#   serial, 44.1 against 54.7 pipelined): transfers and kernel launches on small tensors, per frame.
# - "recording": the force model over a processed recording (`predict`): a fraction of a second of CPU
#   for a recording that took minutes to process, less than starting CUDA in the process costs.
# - "training": Lightning's fit and test: the `colon` study (3 seeds) trained and tested in 102 s on the
#   GPU (6-10 min a run on 2 CPU cores), the force network at 138,000 frames/s eager fp32, batch 16.
WORK = ("frames", "recording", "training")
AUTO_ON_CUDA = {"frames": "cpu", "recording": "cpu", "training": "cuda"}


def auto_device(work: str, cuda_available: bool) -> str:
    """What `--device auto` picks for `work` (one of WORK) given whether CUDA is there."""
    if work not in AUTO_ON_CUDA:
        raise ValueError(f"work {work!r} is not one of {', '.join(WORK)}")
    return AUTO_ON_CUDA[work] if cuda_available else "cpu"


def resolve_device(name: str | None, work: str = "frames") -> str:
    """'cpu', 'cuda' or 'cuda:N' for a `--device` value (None: cpu) and the kind of work it is for
    (`WORK`; only `auto` depends on it)."""
    import torch  # here, not at the top: the commands' parsers import this module, `vfdata --help` no torch

    name = (name or "cpu").strip().lower()
    if name == "auto":
        return auto_device(work, torch.cuda.is_available())
    if name == "cpu":
        return "cpu"
    if name == "cuda" or (name.startswith("cuda:") and name[5:].isdigit()):
        if not torch.cuda.is_available():
            raise VisionForceError(f"--device {name}: no CUDA device here (torch sees none; torch "
                                   f"{torch.__version__}, CUDA build {torch.version.cuda or 'none'}): use --device cpu "
                                   "or auto")
        index = int(name[5:]) if ":" in name else 0
        if index >= torch.cuda.device_count():
            raise VisionForceError(f"--device {name}: only {torch.cuda.device_count()} CUDA device(s) here")
        return name
    raise VisionForceError(f"--device {name}: not one of cpu, cuda, cuda:N, auto")


def lightning_accelerator(device: str) -> str:
    """The Lightning `trainer.accelerator` of a resolved device."""
    return "cpu" if device == "cpu" else "gpu"



def tracker_device_options(tracker: str, device: str) -> dict:
    """The tracker options that put `tracker` on a resolved `device`: none for the CPU (options, and so
    the derived files' provenance, stay as they were), `device` for the geometry trackers."""
    if device == "cpu":
        return {}
    if tracker not in GPU_TRACKERS:
        raise VisionForceError(f"--device {device}: the '{tracker}' tracker runs on the CPU only (on a GPU: "
                               f"{', '.join(GPU_TRACKERS)})")
    return {"device": device}


def shared_device_options(tracker: str, device: str) -> dict:
    """The tracker options for a job whose model runs on `device` (resolved): the geometry trackers go
    there too, a tracker without a GPU path (KLT) stays on the CPU."""
    return tracker_device_options(tracker, device) if tracker in GPU_TRACKERS else {}
