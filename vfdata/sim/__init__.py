"""The simulator behind `vfdata synth`: tissue-manipulation recordings with ground truth.

`synthesize(preset, out_dir, seed=0, workers=1)` writes raw recording folders (the layout `vfdata
convert` reads) with a `ground_truth/` folder each, and the dataset manifest. See docs/synthetic.md.
"""

from vfdata.sim.presets import PRESETS
from vfdata.sim.synthesize import synthesize

__all__ = ["PRESETS", "synthesize"]
