"""Train the heading reader (:mod:`pfnet.data.heading`) and write its file.

Training partials: a data set's training shapes, a fresh cloud from each pool, cut by the
``turned`` crop (one of the paper's five viewpoints turned to a random side, the shape in
its own heading: what a ``heading``-frame model trains on), each put in its aligned frame;
the target is the angle of its main axis in the data set's frame, as soft bins
(:func:`pfnet.models.heading.soft_targets`). Validation: the test protocol's partials of
another data set's val split (sample ``i`` cut at ``VIEWPOINTS[i % 5]``), each turned by an
angle of its own (seeded), scored by the heading read back (the reader's reading subtracted
from the turned partial's main axis, as :meth:`~pfnet.data.heading.HeadingReader.headings`
does). The best validation state is written (atomically) after every evaluation, with its
card.

    python benchmarks/heading_reader.py --data data/sh3d-all --val-data data/sh3d \\
        --steps 3000 --out python/pfnet/weights/heading/sh3d.safetensors
    python benchmarks/heading_reader.py --evaluate python/pfnet/weights/heading/sh3d.safetensors \\
        --val-data data/sh3d --split test
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from pfnet.data import load_split, test_protocol_crop
from pfnet.data.heading import aligned_input, decode_headings, load_reader
from pfnet.data.scan_frame import up_rotation


def reader_input(partial: np.ndarray, points: int) -> tuple[np.ndarray, float]:
    """A y-up partial as the reader reads it: its aligned frame sampled as the reader
    samples (farthest points from point 0), and its main axis's angle."""
    from pfnet.data.sampling import fixed_size

    aligned, angle = aligned_input(partial)
    return fixed_size(aligned, points), angle


def angle_errors(read: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Degrees between read and true headings, the short way round (0 to 180)."""
    return np.degrees(np.abs(np.angle(np.exp(1j * (np.asarray(read) - np.asarray(true))))))


def validation_set(data: Path, split: str, points: int, seed: int):
    """``(inputs, main_angles, turns, categories)`` of the val partials, each turned by its
    own angle: the reader's inputs, the turned partials' main axes, the true turns."""
    clouds = load_split(data, split)
    partial, _ = test_protocol_crop(np.asarray(clouds.points), 0.25)
    turns = np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi, len(partial))
    read = [
        reader_input(np.asarray(p, np.float64) @ up_rotation(t, 1).T, points)
        for p, t in zip(partial, turns, strict=True)
    ]
    inputs = np.stack([x for x, _ in read])
    main_angles = np.array([a for _, a in read])
    return inputs, main_angles, turns, np.asarray(clouds.category).astype(str)


def summary(errors: np.ndarray, categories: np.ndarray) -> dict:
    """Median error and the shares within 15°, 30° and 45°, overall and per category."""

    def one(e):
        return {
            "n": int(len(e)),
            "median_deg": round(float(np.median(e)), 1),
            "within_15": round(float(np.mean(e < 15)), 3),
            "within_30": round(float(np.mean(e < 30)), 3),
            "within_45": round(float(np.mean(e < 45)), 3),
        }

    return {
        "all": one(errors),
        "categories": {c: one(errors[categories == c]) for c in sorted(set(categories))},
    }


def evaluate(reader_path: Path, data: Path, split: str, seed: int = 11) -> dict:
    """A reader file on every shape of a split cut at each of the five viewpoints, each
    turned by its own angle: :func:`summary` of the errors, with the shares near a quarter
    and a half turn off (75°–105°, over 165°)."""
    from pfnet.geometry import VIEWPOINTS, crop_by_viewpoint

    reader = load_reader(reader_path)
    clouds = load_split(data, split)
    rng = np.random.default_rng(seed)
    scans, turns, categories = [], [], []
    from pfnet.data import missing_count

    n_missing = missing_count(clouds.n_points, 0.25)
    for cloud, category in zip(np.asarray(clouds.points, np.float32), clouds.category):
        for view in VIEWPOINTS:
            partial, _ = crop_by_viewpoint(cloud, np.asarray(view, np.float32), n_missing=n_missing)
            turns.append(rng.uniform(0.0, 2.0 * math.pi))
            scans.append(partial.astype(np.float64) @ up_rotation(turns[-1], 1).T)
            categories.append(str(category))
    errors = angle_errors(reader.headings(scans), np.array(turns))
    figures = summary(errors, np.asarray(categories))
    figures["quarter_turn_off"] = round(float(np.mean((errors > 75) & (errors < 105))), 3)
    figures["half_turn_off"] = round(float(np.mean(errors > 165)), 3)
    return figures


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="training data set")
    parser.add_argument("--val-data", type=Path, required=True, help="its val split validates")
    parser.add_argument(
        "--evaluate",
        type=Path,
        help="instead of training: score this reader file on --val-data's --split, every "
        "shape cut at the five viewpoints",
    )
    parser.add_argument("--split", default="val", help="the split --evaluate scores (val)")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--eval-every", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1)")
    parser.add_argument("--out", type=Path, help="the reader file to write")
    args = parser.parse_args(argv)
    if args.evaluate is not None:
        print(json.dumps(evaluate(args.evaluate, args.val_data, args.split), indent=2))
        return
    if args.data is None or args.out is None:
        sys.exit("training needs --data and --out")
    if args.steps < 1 or args.batch_size < 2 or args.eval_every < 1:
        sys.exit("--steps and --eval-every must be >= 1, --batch-size >= 2")

    import torch

    from pfnet.data.dataset import CompletionDataset
    from pfnet.models.heading import POINTS, HeadingNet, save_reader, soft_targets

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    train = CompletionDataset(args.data, "train", crop="turned", fresh_points=True, seed=args.seed)
    val_x, val_main, val_turns, val_categories = validation_set(
        args.val_data, "val", POINTS, args.seed + 1
    )
    net = HeadingNet()
    optimiser = torch.optim.Adam(net.parameters(), lr=args.lr)
    milestones = [int(args.steps * 0.6), int(args.steps * 0.85)]
    schedule = torch.optim.lr_scheduler.MultiStepLR(optimiser, milestones, gamma=0.2)
    rng = np.random.default_rng(args.seed)
    order: list[int] = []
    epoch, best, started, log = 0, None, time.perf_counter(), []
    for step in range(1, args.steps + 1):
        if len(order) < args.batch_size:
            epoch += 1
            train.set_epoch(epoch)
            order = list(rng.permutation(len(train)))
        batch = [order.pop() for _ in range(args.batch_size)]
        read = [reader_input(train[i]["partial"].numpy(), POINTS) for i in batch]
        x = np.stack([points for points, _ in read])
        angles = np.array([angle for _, angle in read])
        net.train()
        scores = net(torch.from_numpy(x))
        loss = -(torch.from_numpy(soft_targets(angles)) * torch.log_softmax(scores, 1)).sum(1)
        optimiser.zero_grad()
        loss.mean().backward()
        optimiser.step()
        schedule.step()
        if step % args.eval_every and step != args.steps:
            continue
        net.eval()
        with torch.no_grad():
            val_scores = net(torch.from_numpy(val_x)).numpy()
        headings = (val_main - decode_headings(val_scores)) % (2.0 * math.pi)
        errors = angle_errors(headings, val_turns)
        figures = summary(errors, val_categories)
        entry = {"step": step, "loss": round(float(loss.detach().mean()), 4), **figures["all"]}
        entry["seconds"] = round(time.perf_counter() - started, 1)
        log.append(entry)
        print(entry, flush=True)
        if best is None or figures["all"]["median_deg"] <= best["all"]["median_deg"]:
            best = {**figures, "step": step}
            card = {
                "what": "heading reader: the turn about the up axis of a y-up partial cloud",
                "data": str(args.data),
                "validation": f"{args.val_data} val split, the test protocol's partials "
                "(25 % missing), each turned by its own random angle",
                "recipe": {
                    "steps": args.steps,
                    "batch_size": args.batch_size,
                    "lr": args.lr,
                    "milestones": milestones,
                    "crop": "turned",
                    "input": "the partial in its aligned frame",
                    "seed": args.seed,
                },
                "best": best,
                "log": log,
            }
            save_reader(net, args.out, points=POINTS, card=card)
    load_reader(args.out)  # the file reads back
    print(f"wrote {args.out} (step {best['step']}: {best['all']})")


if __name__ == "__main__":
    main()
