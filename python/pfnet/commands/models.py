"""``pfnet models``: the trained models shipped with this installation."""

from __future__ import annotations

import argparse
import json

HELP = "List the trained models shipped with pfnet (usable as --checkpoint NAME)."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``pfnet models``."""
    parser.add_argument("--json", action="store_true", help="print the model cards as JSON")


def run(args: argparse.Namespace) -> int:
    """Run ``pfnet models``."""
    from pfnet.inference.shipped import DEFAULT_MODEL, shipped_models

    models = shipped_models()
    if args.json:
        cards = [
            {"name": m.name, "default": m.name == DEFAULT_MODEL, "path": str(m.path), **m.card}
            for m in models
        ]
        print(json.dumps(cards, indent=2))
        return 0
    if not models:
        print("no models are shipped with this installation")
        return 0
    for model in models:
        card, config = model.card, model.config
        default = "  (default)" if model.name == DEFAULT_MODEL else ""
        print(f"{model.name}{default}")
        print(f"  {card.get('summary', '')}".rstrip())
        print(f"  network   {_network_line(config)}; {model.size_mb:.1f} MB")
        print(f"  frame     {_frame_line(config)}")
        for scan in card.get("scan") or []:
            if isinstance(scan, dict):
                mirror = scan.get("mirror") or {}
                reach = scan.get("mirror_fill") or 0  # cards before the mirror fill: none
                fill = (
                    f"mirror fill {reach:g}" if reach else "the network's points, --mirror-fill 0"
                )
                print(
                    f"  scans     {scan.get('data', '?')} ({fill}): Pred->GT + GT->Pred x1000 "
                    f"{scan.get('cd_l2', float('nan')):.2f}, "
                    f"F-score@0.01 {scan.get('f_score', float('nan')):.3f} "
                    f"(a mirror of the input: {mirror.get('cd_l2', float('nan')):.2f}, "
                    f"{mirror.get('f_score', float('nan')):.3f})"
                )
        test = card.get("test")
        if isinstance(test, dict):
            print(
                f"  paper     {test.get('data', '?')}: Pred->GT + GT->Pred x1000 "
                f"{test.get('cd_l2', float('nan')):.2f}, "
                f"F-score@0.01 {test.get('f_score', float('nan')):.3f}"
            )
        print(f"  use       pfnet complete SCAN.ply --checkpoint {model.name} --out DIR")
    return 0


def _frame_line(config: dict) -> str:
    """The frame the model's input is given in (:data:`pfnet.data.scan_frame.FRAMES`)."""
    frame = config.get("frame", "shape")
    return {
        "shape": "shape: trained in the complete shape's frame (the paper's protocol); "
        "scans, which lack it, complete worse",
        "scan": "scan: trained on partials in their own centroid and radius, as complete "
        "gives them",
        "aligned": "aligned: trained on partials in their own frame, turned to their main "
        "horizontal axis, as complete gives them",
        "aligned-end": "aligned-end: trained on partials in their own frame, turned to their "
        "main horizontal axis pointing to its sparser end, as complete gives them",
        "aligned-rim": "aligned-rim: trained on partials in their own frame, turned to their "
        "main horizontal axis, the quarter turn that brings the cut's rim nearest +x, as "
        "complete gives them",
        "rim": "rim: trained on partials in their own frame, turned so that the cut's rim "
        "lies at +x, as complete gives them",
        "heading": "heading: trained on partials in their own centroid and radius and the "
        "data set's heading; complete turns each scan back by the heading a reader reads "
        "from it",
    }.get(frame, str(frame))


def _network_line(config: dict) -> str:
    """What the network takes and gives, as the model card in the docs says it: the partial
    cloud's size in, the missing points out (``n_points`` is the complete cloud's size)."""
    from pfnet.data.crops import missing_count

    n_points, ratio = config.get("n_points"), config.get("missing_ratio")
    head = f"{config.get('model')}, width {config.get('width')}"
    if not isinstance(n_points, int) or not isinstance(ratio, float):
        return head
    m = missing_count(n_points, ratio)
    return (
        f"{head}, {n_points - m:,} points in, the missing {m:,} out "
        f"({ratio:.0%} of {n_points:,}-point clouds)"
    )
