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


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("model-info", help="describe a trained model: inputs, training data, force range, band",
                       description=__doc__.split("\n\n", 1)[1])
    p.add_argument("ckpt", type=Path, help="a .ckpt file, or a run folder (its best checkpoint)")
    p.add_argument("--json", action="store_true", help="print the card as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # here, not at the top: checkpoints need torch; `vfdata --help` starts without it
    from vfdata.errors import InputError
    from vfmodels.inference.trained_model import TrainedModel
    from vfmodels.training.model_card import card_text, read_model_card

    card = read_model_card(args.ckpt)
    try:
        TrainedModel.load(card["file"])
        card["runs_frame_by_frame"] = True
    except InputError as exc:  # a model predict and live cannot run: say why, it is still a model
        card["runs_frame_by_frame"] = False
        card["why_not_frame_by_frame"] = str(exc).partition(": ")[2] or str(exc)
    if args.json:
        print(json.dumps(card, indent=2))
        return 0
    print(card_text(card))
    print("predict:    " + ("runs in `vfdata predict` and `vfdata live`" if card["runs_frame_by_frame"]
                            else f"not in `vfdata predict` or `vfdata live`: {card['why_not_frame_by_frame']}"))
    return 0
