"""Clips for the force models, in the order data flows: `spec` (ClipSpec, the one option set),
`tokens` (pure array functions: tracks -> tokens), `decode` (one recording -> arrays), `dataset`
(ForceClipDataset, torch) and `datamodule` (ForceDataModule, Lightning)."""

from vfdata.clips.spec import ClipSpec

__all__ = ["ClipSpec"]
