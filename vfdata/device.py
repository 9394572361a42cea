"""Where the torch work runs: `--device cpu|cuda|auto` (the tracker's SIREN fit and nearest
neighbours, the force model, the image baselines; training through Lightning's accelerator).

CPU is the default and the tested path; `auto` picks CUDA when torch sees a CUDA device; asking for
`cuda` (or `cuda:N`) on a machine without one is one line naming the option, before any work."""

from __future__ import annotations

from vfdata.errors import VisionForceError

DEVICES = ("cpu", "cuda", "auto")
DEVICE_HELP = ("where the tracker's SIREN fit and nearest neighbours and the force model run: cpu (default), "
               "cuda (cuda:N), or auto (CUDA when present)")


def resolve_device(name: str | None) -> str:
    """'cpu', 'cuda' or 'cuda:N' for a `--device` value (None: cpu)."""
    import torch

    name = (name or "cpu").strip().lower()
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
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


GPU_TRACKERS = ("geometry", "geometry+")


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
