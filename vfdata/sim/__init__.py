"""The simulator behind `vfdata synth`: tissue-manipulation recordings with ground truth.

`synthesize(preset, out_dir, seed=0, workers=1)` writes raw recording folders (the layout `vfdata
convert` reads) with a `ground_truth/` folder each, and the dataset manifest. See docs/synthetic.md.

`synthesize` loads on first use: it brings the renderer's compiled kernels (numba), which the rest of
`vfdata` never needs, and the command line only reads `PRESETS` (vfdata.sim.presets, plain data).
"""

from __future__ import annotations

import sys
import types

from vfdata.sim.presets import PRESETS

__all__ = ["PRESETS", "synthesize"]


class _Simulator(types.ModuleType):
    """This package, with `synthesize` the function, loaded on first use.

    A property rather than a module `__getattr__`: importing the submodule `vfdata.sim.synthesize`
    binds its name on the package, which would shadow the function for later `from vfdata.sim import
    synthesize`; the setter leaves the name to the function (as the package's eager import did)."""

    @property
    def synthesize(self):
        from vfdata.sim.synthesize import synthesize

        return synthesize

    @synthesize.setter
    def synthesize(self, _submodule) -> None:
        pass


sys.modules[__name__].__class__ = _Simulator
