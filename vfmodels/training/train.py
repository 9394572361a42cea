"""Train, test and run the force models from YAML configs: Lightning's CLI, set up for VisionForce.

    python train.py fit --config configs/visionforce.yaml
    python train.py test --config configs/visionforce.yaml --ckpt_path best
    python train.py predict --config configs/visionforce.yaml --ckpt_path best

`predict` writes `/force/estimate` for each recording of the predict split (the test split unless
`--data.predict_split` says otherwise) into `<id>.force.mcap` beside the recording, or in
`--prediction_writer.output_dir`; an existing file is kept unless `--prediction_writer.overwrite true`.

Every run lives in `trainer.default_root_dir` (e.g. runs/visionforce): checkpoints/ (best by
val/loss, and last.ckpt), csv/version_N/metrics.csv, tb/version_N/ (TensorBoard) and the resolved
config. `--ckpt_path best` also works in a later process: it is looked up in that run's checkpoints/.
See docs/models.md (configs, ablations, baselines, multi-GPU/multi-node).
"""

from __future__ import annotations

import copy
import inspect
import sys
from pathlib import Path

from jsonargparse.typing import PositiveInt
from lightning.pytorch import LightningDataModule
from lightning.pytorch.callbacks import ProgressBar
from lightning.pytorch.cli import LightningCLI
from torch import nn

from vfdata.clips.datamodule import ForceDataModule  # noqa: F401 - so that `--data.help ForceDataModule` resolves
from vfdata.errors import InputError, VisionForceError
from vfdata.threads import DEFAULT_THREADS, THREADS_HELP, set_threads
from vfmodels.networks.registry import MODELS, class_path
from vfmodels.training.checkpoint import ResumableCheckpoint, best_checkpoint, read_checkpoint
from vfmodels.training.cli_errors import ForceArgumentParser
from vfmodels.training.early_stopping import ValidationEarlyStopping
from vfmodels.training.epoch_timer import EpochTimer
from vfmodels.training.prediction_writer import ForceEstimateWriter
from vfmodels.training.progress import RunProgressBar
from vfmodels.training.quiet import quiet_lightning
from vfmodels.training.regressor import ForceRegressor
from vfmodels.training.run_folder import closing_line, remove_new_entries, run_entries

DESCRIPTION = ("VisionForce: train, test and run the force models (Set Transformer-LSTM on tracked tissue "
               "points, and the baselines) on processed recordings; configs in configs/, docs in docs/models.md.")


def adopt_normalisation(model: ForceRegressor, datamodule: LightningDataModule) -> None:
    """Give the model the training split's statistics before fitting starts, so that callbacks that copy
    the model when fit begins (EMAWeightAveraging) copy buffers of the right shape."""
    datamodule.setup("fit")
    stats = getattr(datamodule, "normalisation", None)
    if stats is not None:
        model.set_normalisation(**stats)


def _regressor_hparams() -> set[str]:
    """What ForceRegressor saves as hyper_parameters: its plain arguments. Lightning's CLI parses a
    checkpoint's hyper_parameters into the model's config, so anything else (a class_path) could choose
    code to build."""
    return (set(inspect.signature(ForceRegressor.__init__).parameters) - {"self", "model"}) | {"_instantiator"}


def check_checkpoint(ckpt_path: str | Path | None) -> None:
    """An InputError naming a checkpoint file that is missing, damaged, holds pickled code, is not a
    checkpoint or whose hyper_parameters name anything but ForceRegressor's plain arguments, before
    Lightning reads it (its errors are tracebacks). Lightning's own names ("last", "hpc", "registry...")
    are left to it; "best" is resolved to a file before this."""
    if ckpt_path is None or str(ckpt_path) in ("last", "hpc") or str(ckpt_path).startswith("registry"):
        return
    checkpoint = read_checkpoint(ckpt_path)
    if not isinstance(checkpoint.get("state_dict"), dict):
        raise InputError(ckpt_path, "not a Lightning checkpoint (no 'state_dict'): pass a checkpoint train.py wrote")
    hparams = checkpoint.get("hyper_parameters", {})
    if not isinstance(hparams, dict):
        raise InputError(ckpt_path, "the checkpoint's hyper_parameters are not a mapping")
    allowed = _regressor_hparams()
    foreign = sorted(str(k) for k, v in hparams.items()
                     if k not in allowed or not isinstance(v, (bool, int, float, str, type(None))))
    if foreign:
        raise InputError(ckpt_path, f"the checkpoint's hyper_parameters hold {foreign}, which are not ForceRegressor's "
                                    f"plain arguments ({', '.join(sorted(allowed - {'_instantiator'}))}); refusing to "
                                    "build from them")


def check_checkpoint_fits(ckpt_path: str | Path, regressor: ForceRegressor) -> None:
    """An InputError naming the checkpoint when its weights do not fit the model the --config builds (a
    point-cloud checkpoint under proposed.yaml, the same network at other sizes): which model it holds
    against the config's, instead of Lightning's `Error(s) in loading state_dict for ForceRegressor`."""
    if ckpt_path is None or not Path(ckpt_path).is_file():
        return  # Lightning's own names ("last", "hpc", ...) are left to it
    checkpoint = read_checkpoint(ckpt_path)
    try:  # on a copy, exactly as Lightning will load it (strict; the statistics' shapes adopted)
        copy.deepcopy(regressor).load_state_dict(checkpoint["state_dict"])
        return
    except RuntimeError as exc:
        detail = str(exc).splitlines()[1].strip() if len(str(exc).splitlines()) > 1 else str(exc)
    saved = checkpoint.get("force_model") if isinstance(checkpoint.get("force_model"), dict) else {}
    held, built = _model_name(saved.get("class_path")), _model_name(class_path(regressor.model))
    ours = dict(getattr(regressor.model, "config", {}))
    theirs = saved.get("init_args") if isinstance(saved.get("init_args"), dict) else {}
    if not saved:
        what = f"holds weights of another model than the --config's {built} ({detail})"
    elif held != built:
        what = f"holds a {held} model; the --config builds a {built}"
    else:
        keys = [k for k in dict.fromkeys([*theirs, *ours]) if theirs.get(k) != ours.get(k)]
        what = (f"holds a {held}({_args(theirs, keys)}); the --config builds a {built}({_args(ours, keys)})" if keys
                else f"holds a {held} whose weights do not fit the --config's ({detail})")
    raise InputError(ckpt_path, f"{what}: use a checkpoint with the config it was trained with (its run saved it as "
                                "csv/version_N/config.yaml)")


def _config_network(model_config) -> nn.Module | None:
    """The network a parsed config's `model.model` builds, when it is one of `vfmodels.networks.registry`'s (None
    otherwise: the check then waits for the CLI to build it). Pretrained-weight files are not read."""
    network = getattr(model_config, "model", None)
    name = str(getattr(network, "class_path", "")).rpartition(".")[2]
    if name not in MODELS or not str(network.class_path).startswith("vfmodels."):
        return None
    init_args = dict(vars(network.init_args)) if getattr(network, "init_args", None) is not None else {}
    if "weights_path" in init_args:
        init_args["weights_path"] = None
    try:
        return MODELS[name](**init_args)
    except (TypeError, ValueError):
        return None  # the CLI says what is wrong with the arguments when it builds the model


def _model_name(path: object) -> str:
    return str(path or "model").rpartition(".")[2]


def _args(values: dict, keys: list[str]) -> str:
    return ", ".join(f"{k}={values.get(k)}" for k in keys)


class ForceCLI(LightningCLI):
    def __init__(self, *args, argv: list[str] | None = None, **kwargs) -> None:
        self.argv = list(sys.argv[1:] if argv is None else argv)  # for the closing line's test command
        self._existed: set[Path] | None = None
        super().__init__(*args, args=argv, **kwargs)

    def add_arguments_to_parser(self, parser) -> None:
        parser.description = DESCRIPTION
        parser.epilog = ("The data and network options: `--data.help ForceDataModule` (and the ClipSpec under "
                         "--data.spec), `--model.model.help SetTransformerLSTM` (or RGBResNet3D, DepthViTLSTM).")
        parser.add_argument("--threads", type=PositiveInt | None, default=DEFAULT_THREADS,
                            help=THREADS_HELP + "; null leaves torch's default")
        # Keep the checkpoint with the lowest validation loss, and last.ckpt after every epoch for resuming.
        parser.add_lightning_class_args(ResumableCheckpoint, "checkpoint")
        # Stop when the monitored validation loss has not improved for `patience` epochs (null: every epoch).
        parser.add_lightning_class_args(ValidationEarlyStopping, "early_stopping")
        # `predict` writes <id>.force.mcap (/force/estimate) beside each recording or in output_dir.
        parser.add_lightning_class_args(ForceEstimateWriter, "prediction_writer")
        # time/epoch_s and time/epoch_cpu_s in the logs (a run's wall time survives resuming).
        parser.add_lightning_class_args(EpochTimer, "epoch_timer")
        parser.set_defaults({
            "checkpoint.monitor": "val/loss",
            "checkpoint.mode": "min",
            "checkpoint.save_last": True,
            "checkpoint.filename": "epoch{epoch:03d}-val_loss{val/loss:.5f}",
            "checkpoint.auto_insert_metric_name": False,
            "trainer.max_epochs": 60,
            "trainer.default_root_dir": "runs/force",
        })
        parser.link_arguments("checkpoint.monitor", "early_stopping.monitor")
        parser.link_arguments("checkpoint.mode", "early_stopping.mode")
        parser.link_arguments(
            "trainer.default_root_dir", "checkpoint.dirpath", compute_fn=lambda root: str(Path(root) / "checkpoints")
        )

    def before_instantiate_classes(self) -> None:
        cfg = self.config[self.subcommand] if self.subcommand else self.config
        set_threads(cfg.get("threads", DEFAULT_THREADS))  # before any data is decoded or model built
        self._existed = run_entries(Path(cfg.trainer.default_root_dir))
        # CSV and TensorBoard logs in the run folder unless the config names its own loggers.
        if cfg.trainer.logger in (None, True):
            root = cfg.trainer.default_root_dir
            cfg.trainer.logger = [
                {"class_path": "lightning.pytorch.loggers.CSVLogger", "init_args": {"save_dir": root, "name": "csv"}},
                {"class_path": "lightning.pytorch.loggers.TensorBoardLogger",
                 "init_args": {"save_dir": root, "name": "tb"}},
            ]

    def _resolve_checkpoint(self) -> None:
        kwargs = self.config_init[self.subcommand]
        callback = self.trainer.checkpoint_callback
        if kwargs.get("ckpt_path") == "best" and callback is not None and not callback.best_model_path:
            kwargs["ckpt_path"] = str(best_checkpoint(callback.dirpath))
        check_checkpoint(kwargs.get("ckpt_path"))
        check_checkpoint_fits(kwargs.get("ckpt_path"), self.model)
        # Lightning's own load then reads tensors only too, whatever torch's default (pyproject: torch>=2.4).
        kwargs["weights_only"] = True

    def _parse_ckpt_path(self) -> None:
        # Lightning reads the checkpoint here, before any hook, to merge its hyper_parameters into the config.
        subcommand = self.config.get("subcommand")
        if subcommand:
            ckpt_path = self.config[subcommand].get("ckpt_path")
            if ckpt_path and ckpt_path != "best":
                check_checkpoint(ckpt_path)
        super()._parse_ckpt_path()
        if subcommand and ckpt_path and ckpt_path != "best":
            # Before the trainer starts (and says which accelerators it found): the one line comes alone.
            network = _config_network(self.config[subcommand].get("model"))
            if network is not None:
                check_checkpoint_fits(ckpt_path, ForceRegressor(network))

    before_validate = before_test = before_predict = _resolve_checkpoint

    def before_fit(self) -> None:
        self._resolve_checkpoint()
        adopt_normalisation(self.model, self.datamodule)
        doubtful = getattr(self.datamodule, "doubtful_recordings", None)
        if doubtful and self.trainer.is_global_zero:  # `vfdata experiment` leaves them out; here the user chose
            named = ", ".join(f"{rid} ({', '.join(reasons)})" for rid, reasons in doubtful.items())
            print(f"train.py: warning: {self.datamodule.manifest.path}: training and validation include recordings "
                  f"`vfdata process` judged doubtful: {named}; their object frame, and so their labels, may be wrong "
                  "(docs/reconstruction.md, \"How sure\")", file=sys.stderr, flush=True)

    def after_fit(self) -> None:
        if self.trainer.is_global_zero and not self.trainer.fast_dev_run:
            print(closing_line(self.trainer, self.argv), flush=True)

    def _instantiate_trainer(self, config: dict, callbacks: list):
        # The whole run's remaining time in the progress bar (Lightning's bar shows only the epoch's).
        has_bar = any(isinstance(c, ProgressBar) for c in [*(config.get("callbacks") or []), *callbacks])
        if config.get("enable_progress_bar") is not False and not has_bar:
            callbacks = [*callbacks, RunProgressBar()]
        return super()._instantiate_trainer(config, callbacks)

    def _run_subcommand(self, subcommand: str) -> None:
        try:
            super()._run_subcommand(subcommand)
        except BaseException:
            if subcommand == "fit" and self.trainer.global_step == 0 and self.trainer.is_global_zero:
                remove_new_entries(Path(self.trainer.default_root_dir), self._existed)
            raise


def make_cli(args: list[str] | None = None, run: bool = True) -> ForceCLI:
    quiet_lightning()
    return ForceCLI(ForceRegressor, LightningDataModule, subclass_mode_data=True,
                    save_config_kwargs={"overwrite": True}, argv=args, run=run, parser_class=ForceArgumentParser,
                    parser_kwargs={"description": DESCRIPTION})


def _named_error(exc: BaseException) -> VisionForceError | None:
    """Our error behind `exc`: jsonargparse wraps what a class's __init__ raises (a missing manifest) in
    ValueErrors of its own, several levels deep."""
    seen: set[int] = set()
    pending = [exc]
    while pending:
        current = pending.pop()
        if current is None or id(current) in seen:
            continue
        seen.add(id(current))
        if isinstance(current, VisionForceError):
            return current
        pending += [current.__cause__, current.__context__]
    return None


def main(args: list[str] | None = None) -> None:
    """The CLI; every failure ends in one line on stderr and exit 1 (`--debug`: the traceback)."""
    # Lightning warns when args are given as well as sys.argv: strip --debug from the one in use.
    given = sys.argv if args is None else args
    debug = "--debug" in given
    given[:] = [a for a in given if a != "--debug"]
    try:
        make_cli(args)
    except Exception as exc:
        if debug:
            raise
        named = _named_error(exc)
        if named is not None:
            print(f"train.py: error: {named}", file=sys.stderr)
        else:  # a bug or an environment problem, not bad input: one line, and the way to learn more
            text = (str(exc).strip().splitlines() or [""])[0]
            print(f"train.py: error: {type(exc).__name__}: {text} (run `python train.py --debug ...` for the "
                  "traceback)", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":  # `python -m vfmodels.training.train ...`: train.py for an installed package
    main()
