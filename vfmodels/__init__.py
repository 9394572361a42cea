"""Force models: the proposed Set Transformer-LSTM, the image baselines, the LightningModule that
trains any of them, and the paper's metrics."""

from vfmodels.baselines import DepthViTLSTM, RGBResNet3D
from vfmodels.metrics import force_metrics, grouped_force_metrics
from vfmodels.regressor import ForceRegressor
from vfmodels.set_transformer import SetTransformerLSTM

__all__ = [
    "DepthViTLSTM",
    "ForceRegressor",
    "RGBResNet3D",
    "SetTransformerLSTM",
    "force_metrics",
    "grouped_force_metrics",
]
