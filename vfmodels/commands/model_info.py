"""`vfdata model-info CKPT`: what a trained model is and what it has seen, from its checkpoint alone.

Prints what the checkpoint says of the model: the network, the inputs it expects, the recordings it was
trained and validated on (and any of them judged doubtful), the force range training covered (N), the
band's calibration, how low the training tissues hang, the run's test figures, and whether `vfdata
predict` and `vfdata live` can run it. `--json` writes the same card as JSON
(`vfmodels.training.model_card`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vfdata.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("model-info", help="describe a trained model: inputs, training data, force range, band",
                       description=__doc__.split("\n\n", 1)[1])
    p.add_argument("ckpt", type=Path, help="a .ckpt file, or a run folder (its best checkpoint)")
    p.add_argument("--json", action="store_true", help="print the card as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # here, not at the top: checkpoints need torch; `vfdata --help` starts without it
    from vfmodels.experiment.report import read_doubtful
    from vfmodels.inference.trained_model import TrainedModel
    from vfmodels.training.checkpoint import read_checkpoint
    from vfmodels.training.model_card import card_text, checkpoint_of, model_card

    ckpt, run_dir = checkpoint_of(args.ckpt)
    checkpoint = read_checkpoint(ckpt)  # once: the card and the frame-by-frame check read the same contents
    card = model_card(checkpoint, ckpt, run_dir)
    tracker = card["inputs"].get("tracker")
    card["training"]["left_out"] = [
        {"id": str(d["id"]), "split": str(d["split"]), "reasons": [str(r) for r in d["reasons"]]}
        for d in read_doubtful(experiment_folder(ckpt)) if d.get("left_out") and d.get("tracker") in (tracker, None)]
    try:
        TrainedModel.load(ckpt, checkpoint=checkpoint)
        card["runs_frame_by_frame"] = True
    except InputError as exc:  # a model predict and live cannot run: say why, it is still a model
        card["runs_frame_by_frame"] = False
        card["why_not_frame_by_frame"] = str(exc).partition(": ")[2] or str(exc)
    if args.json:
        print(json.dumps(card, indent=2))
        return 0
    print(card_text(card))
    if card["training"]["left_out"]:
        print(f"{'left out:':12}" + ", ".join(f"{d['id']} ({d['split']}; {', '.join(d['reasons'])})"
                                             for d in card["training"]["left_out"])
              + ": judged doubtful, so `vfdata experiment` did not train or validate on them")
    print("predict:    " + ("runs in `vfdata predict` and `vfdata live`" if card["runs_frame_by_frame"]
                            else f"not in `vfdata predict` or `vfdata live`: {card['why_not_frame_by_frame']}"))
    return 0


def experiment_folder(ckpt: Path) -> Path:
    """The experiment's OUT a checkpoint lies in (OUT/runs/<variant>/seed<k>/checkpoints/, `runs.run_folder`),
    whose doubtful.json says what the experiment left out; the checkpoint's own folder otherwise (none there)."""
    parents = ckpt.resolve().parents
    inside = len(parents) >= 5 and parents[0].name == "checkpoints" and parents[3].name == "runs"
    return parents[4] if inside else parents[0]
