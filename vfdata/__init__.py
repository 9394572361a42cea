"""VisionForce data: recordings (MCAP), conversion, simulation, reconstruction, tracking, datasets.

`vfdata.Recording` is the reader; `vfdata.ForceClipDataset` and `vfdata.ForceDataModule` (which
import torch and Lightning) load on first use."""

__version__ = "0.1.0"

__all__ = ["Recording", "ForceClipDataset", "ForceDataModule", "__version__"]


def __getattr__(name: str):
    if name == "Recording":
        from vfdata.recording.reader import Recording

        return Recording
    if name in ("ForceClipDataset", "ForceDataModule"):
        from vfdata import datasets

        return getattr(datasets, name)
    raise AttributeError(f"module 'vfdata' has no attribute {name!r}")
