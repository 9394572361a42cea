"""Force models and everything built on them, in the order data flows: the networks (`networks/`:
`set_transformer`, `baselines`, `decoder`, `ridge`, `registry`), how good and how sure an estimate is
(`evaluation/`: `metrics`, `band`), training (`training/`: the LightningModule that trains any network,
`regressor`, and `train`, the LightningCLI behind train.py, with its callbacks), estimation with a
trained model (`inference/`: `trained_model`, `predict`, `live`, `stream`, `live_session`, `overlay`), experiments
(`experiment/`), reports (`reports/`) and the model commands of `vfdata` (`commands/`).

The model classes load on first use (`vfmodels.SetTransformerLSTM`, ...), so that command-line tools
can read the variant registry without importing torch."""

import importlib

__all__ = ["DepthViTLSTM", "ForceRegressor", "RGBResNet3D", "SetTransformerLSTM", "force_metrics",
           "grouped_force_metrics"]

_WHERE = {
    "DepthViTLSTM": "vfmodels.networks.baselines",
    "RGBResNet3D": "vfmodels.networks.baselines",
    "SetTransformerLSTM": "vfmodels.networks.set_transformer",
    "ForceRegressor": "vfmodels.training.regressor",
    "force_metrics": "vfmodels.evaluation.metrics",
    "grouped_force_metrics": "vfmodels.evaluation.metrics",
}


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(importlib.import_module(_WHERE[name]), name)
    raise AttributeError(f"module 'vfmodels' has no attribute {name!r}")
