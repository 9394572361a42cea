"""VisionForce data: recordings (MCAP), conversion, simulation, reconstruction, tracking, clips.

`vfdata.Recording` is the reader, `vfdata.DerivedRecording` the reader of processed files,
`vfdata.load_manifest` the dataset manifests (`Manifest.split("train")` the recordings of a split) and
`vfdata.ClipSpec` how clips are made; `vfdata.denormalise_force` turns a network's output into N;
`vfdata.ForceClipDataset` and `vfdata.ForceDataModule` (torch, Lightning) load on first use so that
the command line starts without them."""

import importlib

__version__ = "0.1.0"

__all__ = ["ClipSpec", "DerivedRecording", "ForceClipDataset", "ForceDataModule", "Manifest", "ManifestEntry", "SPLITS",
           "Recording", "denormalise_force", "load_manifest", "normalise_force", "normalise_input", "__version__"]

_WHERE = {
    "Recording": "vfdata.recording.reader",
    "DerivedRecording": "vfdata.recording.derived",
    "load_manifest": "vfdata.manifest",
    "Manifest": "vfdata.manifest",
    "ManifestEntry": "vfdata.manifest",
    "SPLITS": "vfdata.manifest",
    "normalise_input": "vfdata.clips.normalisation",
    "normalise_force": "vfdata.clips.normalisation",
    "denormalise_force": "vfdata.clips.normalisation",
    "ClipSpec": "vfdata.clips.spec",
    "ForceClipDataset": "vfdata.clips.dataset",
    "ForceDataModule": "vfdata.clips.datamodule",
}


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(importlib.import_module(_WHERE[name]), name)
    raise AttributeError(f"module 'vfdata' has no attribute {name!r}")
