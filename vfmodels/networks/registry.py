"""The force models a checkpoint may name. `ForceRegressor.load` builds a model only from this
registry: a checkpoint is data, and a class path taken from it must never pick code to run."""

from __future__ import annotations

import inspect
from pathlib import Path

from torch import nn

from vfdata.errors import InputError
from vfmodels.networks.baselines import DepthViTLSTM, RGBResNet3D
from vfmodels.networks.set_transformer import SetTransformerLSTM

MODELS: dict[str, type[nn.Module]] = {cls.__name__: cls for cls in (SetTransformerLSTM, RGBResNet3D, DepthViTLSTM)}


def class_path(model: nn.Module) -> str:
    """The name a checkpoint stores for `model` (its module and class)."""
    cls = type(model)
    return f"{cls.__module__}.{cls.__qualname__}"


def build_model(path: Path, saved_class_path: str, init_args: dict) -> nn.Module:
    """The registered model named by a checkpoint's class path, built with its saved arguments."""
    name = str(saved_class_path).rpartition(".")[2]
    cls = MODELS.get(name)
    if cls is None or not str(saved_class_path).startswith("vfmodels."):
        raise InputError(path, f"the checkpoint names model '{saved_class_path}', which is not one of VisionForce's "
                               f"({', '.join(MODELS)}); refusing to run it")
    allowed = set(inspect.signature(cls.__init__).parameters) - {"self"}
    unknown = sorted(set(init_args) - allowed)
    if unknown:
        raise InputError(path, f"the checkpoint gives {name} unknown arguments {unknown}")
    try:
        return cls(**init_args)
    except (TypeError, ValueError) as exc:
        raise InputError(path, f"the checkpoint's {name} arguments are invalid ({exc})") from None
