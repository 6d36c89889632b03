"""Turn a training run's ``best.pt`` into a shipped model file with a measured model card.

    python benchmarks/ship_model.py RUN/best.pt --name sh3d-small \\
        --train-data data/sh3d-all --test-data data/sh3d --summary "..." --recipe "..."

The float16 file is written first, then *it* (not the float32 checkpoint) predicts the test
split of ``--test-data`` with the deterministic test protocol and is scored (missing region,
at the model's missing ratio); those figures, the training data's catalogues, licences and
per-model credits go into the card, and the file is written again with the card to
``python/pfnet/weights/NAME``.
The test split must be one the run never trained on: the script refuses if a test shape's
name is among the training data's.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from pfnet.data import load_split, read_manifest
from pfnet.evaluation.scoring import evaluate_predictions
from pfnet.inference.checkpoint import write_shipped
from pfnet.inference.predict import predict_split
from pfnet.inference.shipped import SUFFIX, WEIGHTS_DIR


def _data_summary(data: Path) -> dict:
    """Where a data set's training shapes come from, for the card (creators are in credits)."""
    manifest = read_manifest(data)
    splits = manifest.get("splits") or {}
    shapes = splits["train"]["total"] if "train" in splits else len(load_split(data, "train"))
    return {
        "source": manifest.get("source"),
        "shapes": shapes,
        "categories": manifest.get("categories"),
        "licenses": [
            {k: v for k, v in licence.items() if k != "creators"}
            for licence in manifest.get("licenses") or []
        ],
    }


def _scan_card(path: Path) -> dict:
    """The scan protocol's figures for the card, from a JSON of benchmarks/scan_protocol.py."""
    document = json.loads(path.read_text())
    results = document["results"]
    model = results["complete (scan protocol)"]
    mirror = results["mirror of the input (learns nothing)"]
    return {
        "data": f"{Path(document['data']).name} {document['split']} split, "
        + ("what a depth camera sees, " if document.get("scans") == "scanner" else "")
        + f"{document['missing_ratio']:.0%} missing, each scan turned, scaled and moved at random, "
        f"{document['up']}-up, through pfnet complete",
        "up": document["up"],
        "mirror_fill": document.get("mirror_fill", 0.0),  # complete's --mirror-fill
        "cd_l2": model["mean"]["cd_l2"],
        "f_score": model["mean"]["f_score"],
        "categories": {
            c: {k: v[k] for k in ("cd_l2", "f_score")} for c, v in model["categories"].items()
        },
        "mirror": {"cd_l2": mirror["mean"]["cd_l2"], "f_score": mirror["mean"]["f_score"]},
        "f_wins_over_mirror": document["f_wins_over_mirror"],
        "categories_scored": len(model["categories"]),
    }


def _card_rest(args, mean, evaluation, test, manifest) -> dict:
    """Everything of the card after its summary and scan figures."""
    from pfnet.inference.checkpoint import load_checkpoint

    trained = load_checkpoint(args.checkpoint)[1]
    frame, ratio = getattr(trained, "frame", "shape"), trained.missing_ratio
    given = (
        "the complete shape's frame"
        if frame == "shape"
        else f"each partial in its own ({frame}) frame, unturned"
    )
    rest = {
        "recipe": args.recipe,
        "train_data": _data_summary(args.train_data),
        "test": {
            "data": f"{args.test_data.name} test split ({len(test)} shapes, never trained "
            f"on), {ratio:.0%} missing, the paper's crops, {given}, mean over categories",
            "pred_to_gt": mean["pred_to_gt"],
            "gt_to_pred": mean["gt_to_pred"],
            "cd_l2": mean["pred_to_gt"] + mean["gt_to_pred"],
            "f_score": mean["f_score"],
            "categories": evaluation.report["categories"],
        },
    }
    if args.pretrain_data is not None:
        rest["pretrain_data"] = _data_summary(args.pretrain_data)
    rest["credits"] = manifest.get("credits") or {}
    return rest


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("checkpoint", type=Path, help="best.pt of pfnet train, or a model file")
    parser.add_argument("--name", required=True)
    parser.add_argument("--train-data", type=Path, required=True, help="data set it trained on")
    parser.add_argument("--test-data", type=Path, required=True, help="data set to score on")
    parser.add_argument(
        "--pretrain-data",
        type=Path,
        help="data set the run's --init-from weights were trained on (recorded in the card)",
    )
    parser.add_argument(
        "--scan-protocol",
        type=Path,
        action="append",
        default=[],
        help="a JSON of benchmarks/scan_protocol.py measured on this model (y-up, then z-up): "
        "the card's first figures, what `pfnet complete` gets",
    )
    parser.add_argument(
        "--frame",
        choices=("heading",),
        help="ship a --frame scan --crop turned run in the heading frame (its inputs' frame)",
    )
    parser.add_argument("--summary", required=True, help="one line for `pfnet models`")
    parser.add_argument("--recipe", required=True, help="how it was trained (the command)")
    parser.add_argument("--out-dir", type=Path, default=WEIGHTS_DIR)
    args = parser.parse_args(argv)

    trained_on = {str(n) for n in load_split(args.train_data, "train").name}
    test = load_split(args.test_data, "test")
    leaked = sorted(trained_on & {str(n) for n in test.name})
    if leaked:
        sys.exit(f"refusing: {len(leaked)} test shapes were trained on, e.g. {leaked[:3]}")

    from pfnet.inference.checkpoint import load_checkpoint

    ratio = load_checkpoint(args.checkpoint)[1].missing_ratio  # the paper's crops at the model's
    out = args.out_dir / f"{args.name}{SUFFIX}"
    with tempfile.TemporaryDirectory() as scratch:
        draft = write_shipped(args.checkpoint, Path(scratch) / f"draft{SUFFIX}", frame=args.frame)
        pred = Path(scratch) / "pred"
        predict_split(draft, args.test_data, pred, device="cpu")
        evaluation = evaluate_predictions(pred, args.test_data, missing_ratio=ratio)
    mean = evaluation.report["mean"]
    manifest = read_manifest(args.train_data)
    card: dict = {"summary": args.summary}
    if args.scan_protocol:  # first: what `pfnet complete` gets
        card["scan"] = [_scan_card(path) for path in args.scan_protocol]
    card.update(_card_rest(args, mean, evaluation, test, manifest))
    write_shipped(args.checkpoint, out, card=card, frame=args.frame)
    size = out.stat().st_size / 1e6
    print(json.dumps({k: v for k, v in card.items() if k != "credits"}, indent=2))
    print(f"wrote {out} ({size:.1f} MB); test CD-L2 {card['test']['cd_l2']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
