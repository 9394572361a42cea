"""Force models and everything built on them, in the order data flows: the networks
(`set_transformer`, `baselines`, `decoder`, `registry`), the LightningModule that trains any of
them (`regressor`), training (`train`: the LightningCLI behind train.py), prediction (`predict`,
`live`, `overlay`, `prediction_writer`), experiments (`experiment/`) and reports (`reports/`).

The model classes load on first use (`vfmodels.SetTransformerLSTM`, ...), so that command-line tools
can read the variant registry without importing torch."""

import importlib

__all__ = ["DepthViTLSTM", "ForceRegressor", "RGBResNet3D", "SetTransformerLSTM", "force_metrics",
           "grouped_force_metrics"]

_WHERE = {
    "DepthViTLSTM": "vfmodels.baselines",
    "RGBResNet3D": "vfmodels.baselines",
    "SetTransformerLSTM": "vfmodels.set_transformer",
    "ForceRegressor": "vfmodels.regressor",
    "force_metrics": "vfmodels.metrics",
    "grouped_force_metrics": "vfmodels.metrics",
}


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(importlib.import_module(_WHERE[name]), name)
    raise AttributeError(f"module 'vfmodels' has no attribute {name!r}")
