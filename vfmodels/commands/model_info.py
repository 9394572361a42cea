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
    from vfmodels.inference.trained_model import TrainedModel
    from vfmodels.training.model_card import card_text, read_model_card

    card = read_model_card(args.ckpt)
    card["training"]["left_out"] = experiment_left_out(Path(card["file"]), card["inputs"].get("tracker"))
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
    if card["training"]["left_out"]:
        print(f"{'left out:':12}" + ", ".join(f"{d['id']} ({d['split']}; {', '.join(d['reasons'])})"
                                       for d in card["training"]["left_out"])
              + ": judged doubtful, so `vfdata experiment` did not train or validate on them")
    print("predict:    " + ("runs in `vfdata predict` and `vfdata live`" if card["runs_frame_by_frame"]
                            else f"not in `vfdata predict` or `vfdata live`: {card['why_not_frame_by_frame']}"))
    return 0


def experiment_left_out(ckpt: Path, tracker: str | None) -> list[dict]:
    """The recordings `vfdata experiment` left out of this model's training and validation as doubtful, when
    the checkpoint lies in an experiment's folder (OUT/runs/<variant>/seed<k>/checkpoints/, beside OUT's
    doubtful.json); [] otherwise. The checkpoint names what it trained on; the experiment, what it left out."""
    parents = ckpt.resolve().parents
    if len(parents) < 5 or parents[0].name != "checkpoints" or parents[3].name != "runs":
        return []
    report = parents[4] / "doubtful.json"
    try:
        entries = json.loads(report.read_text()) if report.is_file() else []
        return [{"id": str(d["id"]), "split": str(d["split"]), "reasons": [str(r) for r in d["reasons"]]}
                for d in entries if d.get("left_out") and d.get("tracker") in (tracker, None)]
    except (ValueError, KeyError, TypeError, AttributeError):
        raise InputError(report, "not the doubtful report `vfdata experiment` writes") from None
