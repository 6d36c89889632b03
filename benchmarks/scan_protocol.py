"""The scan protocol, measured through ``pfnet complete`` itself (DESIGN.md §3).

Each test partial of the paper's protocol (sample *i* loses the points nearest
``VIEWPOINTS[i % 5]``; with ``--scans scanner``, what a depth camera sees of it instead:
:func:`pfnet.data.scanner.scanner_test_crop`, sample *i* scanned from test camera *i*, the
hidden points the removed ones) is put in a pose of its own
(:func:`pfnet.data.scan_frame.scan_pose`: a random turn about the up axis, a random scale
and offset; with ``--up z`` stood z-up), saved as ``.npy``, and completed by the ``pfnet
complete`` command in a new process, as a user would. The completions are mapped back
through the poses and scored against the removed points in the data set's frame (CD-L2
×1000, F-score@0.01), beside:

* the same model given the partial in the complete shape's frame (the paper's protocol, what
  ``pfnet predict`` does: information a scan does not have);
* the mirror completion (:mod:`pfnet.data.symmetry`), which learns nothing: the scan, turned
  y-up and normalised in the scan frame, reflected across the vertical plane estimated from
  the scan alone;
* with ``--nearest DATA``, the nearest training crop (:mod:`pfnet.evaluation.nearest`), which
  learns nothing either: the scan looked up among DATA's training shapes cut at the five
  viewpoints from eight sides.

With ``--views 5`` every shape is cut at each of the five viewpoints (or scanned by five test
cameras): scan ``5 i + v`` is shape ``i`` at viewpoint ``v``, in pose ``5 i + v``. Five times
the scans make a steadier mean: on 54 one-view scans a single scan has moved it by 30.

Besides the means, each result gives the median scan's CD-L2 and the share of the CD-L2 sum
that the worst tenth of the scans make (a mean that a few scans make says so), and those scans
by name (``index-category-shape``, as ``--keep`` names its files).

    python benchmarks/scan_protocol.py --data data/sh3d [--checkpoint NAME] [--up z] \\
        [--scans scanner] [--views 5] [--json results/scan-protocol/sh3d-small.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pfnet.data import every_view, load_split, test_protocol_crop
from pfnet.data.scan_frame import UP_AXES, scan_normalisation, scan_pose, to_y_up
from pfnet.data.scanner import scanner_test_crop
from pfnet.data.symmetry import mirror_completion
from pfnet.evaluation.metrics import sample_metrics, summarize
from pfnet.inference.completion import DEFAULT_MIRROR_FILL
from pfnet.io.clouds import read_point_cloud


def complete_through_cli(scans, out, up, checkpoint, runtime, mirror_fill=None):
    """Run ``pfnet complete`` on the scans (saved as .npy) and read back the predictions."""
    inputs = out / "scans"
    inputs.mkdir()
    paths = []
    for i, scan in enumerate(scans):
        path = inputs / f"scan{i:04d}.npy"
        np.save(path, scan)
        paths.append(path)
    command = [sys.executable, "-m", "pfnet.cli", "complete", *map(str, paths)]
    command += ["--out", str(out / "completed"), "--up", up, "--runtime", runtime]
    if checkpoint:
        command += ["--checkpoint", checkpoint]
    if mirror_fill is not None:
        command += ["--mirror-fill", str(mirror_fill)]
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    elapsed = time.perf_counter() - started
    if done.returncode != 0:
        sys.exit(f"pfnet complete failed ({done.returncode}):\n{done.stderr}")
    first_line = done.stdout.splitlines()[0] if done.stdout else ""
    predictions = [
        read_point_cloud(out / "completed" / f"{path.stem}_missing.ply").astype(np.float64)
        for path in paths
    ]
    return predictions, first_line, elapsed


def mirror_predictions(scans, up, n_missing):
    """The mirror completion of each scan, in the scan's coordinates."""
    turn = to_y_up(up)
    out = []
    for scan in scans:
        upright = np.asarray(scan, np.float64) @ turn.T
        frame = scan_normalisation(upright)
        mirrored = mirror_completion(frame.apply(upright), n_missing, up_axis=1)
        out.append((mirrored.astype(np.float64) * frame.radius + frame.centre) @ turn)
    return out


SCANS = ("viewpoint", "scanner")
"""The test partials: the paper's viewpoint crop, or what a depth camera sees."""

DEFAULT_RATIOS = {"viewpoint": 0.25, "scanner": 0.5}
"""The missing ratio of each kind of scan: the paper's; half, about what a camera misses of
SweetHome3D's furniture (docs/data.md)."""


def test_partials(points, scans, ratio):
    """``(partial, removed)`` of a split's complete clouds: the deterministic test protocol of
    the viewpoint crop or of the scanner (y-up, the data sets' axis)."""
    if scans == "scanner":
        return scanner_test_crop(points, ratio)
    return test_protocol_crop(points, ratio)


test_partials.__test__ = False  # a helper, not a pytest test


def shape_frame_predictions(partial, checkpoint, runtime):
    """The model given each partial in the complete shape's frame (the paper's protocol),
    resampled to the model's input size as ``complete`` does (a scanner partial need not have
    the size the model was trained on)."""
    from pfnet.inference.completion import network_input
    from pfnet.inference.predict import predict_missing
    from pfnet.inference.runtimes import load_generator

    loaded = load_generator(checkpoint, runtime=runtime, device="cpu")
    n_input = int(loaded.model.n_points) - int(loaded.model.n_missing)
    batch = np.stack([network_input(np.asarray(p, np.float64), n_input) for p in partial])
    return list(predict_missing(loaded.model, batch.astype(np.float32), 32, "cpu"))


def nearest_predictions(scans, up, bank_data, n_points, n_missing):
    """The nearest training crop of each scan (:mod:`pfnet.evaluation.nearest`), in the
    scan's coordinates."""
    from pfnet.evaluation.nearest import crop_bank, nearest_completion

    bank_clouds = np.asarray(load_split(bank_data, "train").points, np.float32)[:, :n_points]
    bank = crop_bank(bank_clouds, n_missing)
    turn = to_y_up(up)
    return [
        nearest_completion(bank, np.asarray(scan, np.float64) @ turn.T)[0] @ turn for scan in scans
    ]


def score(predictions, removed, categories, labels=None):
    """Per-category and overall means (CD ×1000) of predictions against the removed points,
    with the median scan's CD-L2 and the worst tenth's share of the CD-L2 sum; with
    ``labels`` (one per scan), the worst tenth's scans by name."""
    per_sample = sample_metrics(
        [np.asarray(p, np.float32) for p in predictions], list(removed.astype(np.float32))
    )
    table = summarize(per_sample, categories)
    cd = np.asarray(per_sample["cd_l2"], np.float64) * 1000.0
    order = np.argsort(-cd, kind="stable")
    worst = order[: max(1, round(len(cd) / 10))]
    table["spread"] = {
        "median_cd_l2": float(np.median(cd)),
        "worst_tenth_share": float(cd[worst].sum() / cd.sum()) if cd.sum() > 0 else 0.0,
        "worst_cd_l2": [round(float(cd[i]), 2) for i in worst],
    }
    if labels is not None:
        table["spread"]["worst_scans"] = [str(labels[i]) for i in worst]
    return table


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="a prepared data set")
    parser.add_argument("--split", default="test")
    parser.add_argument(
        "--scans",
        default="viewpoint",
        choices=SCANS,
        help="viewpoint: the paper's crop (default); scanner: what a depth camera sees",
    )
    parser.add_argument(
        "--ratio",
        type=float,
        default=None,
        help="missing ratio (0.25 for viewpoint scans, 0.5 for scanner ones)",
    )
    parser.add_argument("--checkpoint", default=None, help="model (default: the shipped one)")
    parser.add_argument("--runtime", default="auto", choices=("auto", "torch", "onnx"))
    parser.add_argument(
        "--mirror-fill",
        type=float,
        default=None,
        help="complete's --mirror-fill (default: complete's default; 0: the network's points)",
    )
    parser.add_argument("--up", default="y", choices=UP_AXES, help="stand the scans y- or z-up")
    parser.add_argument("--seed", type=int, default=0, help="seed of the poses (0)")
    parser.add_argument(
        "--views",
        type=int,
        choices=(1, 5),
        default=1,
        help="cut each shape at the protocol's one view (1) or at all five (5)",
    )
    parser.add_argument(
        "--no-turn", action="store_true", help="no turn about the up axis (scale and offset only)"
    )
    parser.add_argument(
        "--categories",
        nargs="+",
        default=None,
        help="score these categories' samples only (each keeps its crop and pose of the split)",
    )
    parser.add_argument("--json", type=Path, default=None, help="write the figures here")
    parser.add_argument(
        "--keep",
        type=Path,
        default=None,
        help="save each sample's partial, completion (mapped back) and removed points here",
    )
    parser.add_argument(
        "--nearest",
        type=Path,
        default=None,
        help="also score the nearest training crop among this data set's training shapes",
    )
    parser.add_argument(
        "--no-mirror",
        action="store_true",
        help="leave out the mirror baseline (slow on big splits)",
    )
    args = parser.parse_args(argv)
    if args.ratio is None:
        args.ratio = DEFAULT_RATIOS[args.scans]

    clouds = every_view(load_split(args.data, args.split), args.views)
    points = np.asarray(clouds.points, np.float32)
    partial, removed = test_partials(points, args.scans, args.ratio)
    categories = [str(c) for c in clouds.category]
    labels = [  # a scan's name: its index in the split, its category and shape
        f"{i:03d}-{cat}-{name}"
        for i, (name, cat) in enumerate(zip(clouds.name, categories, strict=True))
    ]
    poses = [
        scan_pose(i, up=args.up, seed=args.seed, turn=not args.no_turn) for i in range(len(points))
    ]
    scans = [pose.apply(p) for pose, p in zip(poses, partial, strict=True)]
    if args.categories:  # a sample keeps the crop and pose its index gives it in the split
        kept = [i for i, c in enumerate(categories) if c in set(args.categories)]
        if not kept:
            sys.exit(f"no {args.split} sample of {args.data} is in {', '.join(args.categories)}")
        partial, removed = partial[kept], removed[kept]
        categories, labels = [categories[i] for i in kept], [labels[i] for i in kept]
        poses, scans = [poses[i] for i in kept], [scans[i] for i in kept]
        points = points[kept]

    with tempfile.TemporaryDirectory() as tmp:
        completed, said, elapsed = complete_through_cli(
            scans, Path(tmp), args.up, args.checkpoint, args.runtime, args.mirror_fill
        )

    results = {
        "complete (scan protocol)": [
            pose.invert(c) for pose, c in zip(poses, completed, strict=True)
        ],
        "same model, shape frame (paper protocol)": shape_frame_predictions(
            partial, args.checkpoint, args.runtime
        ),
    }
    if not args.no_mirror:
        results["mirror of the input (learns nothing)"] = [
            pose.invert(c)
            for pose, c in zip(
                poses, mirror_predictions(scans, args.up, removed.shape[1]), strict=True
            )
        ]
    if args.nearest is not None:
        nearest = nearest_predictions(
            scans, args.up, args.nearest, points.shape[1], removed.shape[1]
        )
        results["nearest training crop (learns nothing)"] = [
            pose.invert(c) for pose, c in zip(poses, nearest, strict=True)
        ]
    tables = {name: score(p, removed, categories, labels) for name, p in results.items()}
    if args.keep is not None:  # in the data set's frame, for `pfnet render --sample`
        args.keep.mkdir(parents=True, exist_ok=True)
        mapped_back = results["complete (scan protocol)"]
        for i, label in enumerate(labels):
            stem = args.keep / label
            np.save(f"{stem}-partial.npy", partial[i].astype(np.float32))
            np.save(f"{stem}-completion.npy", np.asarray(mapped_back[i], np.float32))
            np.save(f"{stem}-removed.npy", removed[i].astype(np.float32))

    print(
        f"{len(points)} {args.split} {args.scans} partials of {args.data} "
        f"({args.ratio:g} missing), {args.up}-up; {said}"
    )
    print(f"pfnet complete: {elapsed:.1f} s for all, in a new process")
    names = list(tables)
    header = "category".ljust(10) + "".join(f" | {n[:28]:>28}" for n in names)
    print(header + "\n" + "-" * len(header))
    rows = [*sorted(tables[names[0]]["categories"]), "mean"]
    for row in rows:
        cells = []
        for name in names:
            table = tables[name]
            values = table["mean"] if row == "mean" else table["categories"][row]
            cells.append(f"{values['cd_l2']:8.2f} CD-L2  F {values['f_score']:.4f}")
        print(row.ljust(10) + "".join(f" | {c:>28}" for c in cells))
    spread = "".join(
        f" | {'median ' + format(tables[n]['spread']['median_cd_l2'], '.2f'):>28}" for n in names
    )
    print("median".ljust(10) + spread)
    share = "".join(
        f" | {'worst tenth ' + format(tables[n]['spread']['worst_tenth_share'], '.0%'):>28}"
        for n in names
    )
    print("of sum".ljust(10) + share)
    spread = tables[names[0]]["spread"]
    print(
        f"the worst tenth of {names[0]}: "
        + ", ".join(
            f"{label} {cd:.1f}"
            for label, cd in zip(spread["worst_scans"], spread["worst_cd_l2"], strict=True)
        )
    )
    wins = None
    if not args.no_mirror:
        model = tables[names[0]]["categories"]
        mirror = tables["mirror of the input (learns nothing)"]["categories"]
        wins = sum(model[c]["f_score"] > mirror[c]["f_score"] for c in model)
        print(f"F-score above the mirror's in {wins} of {len(model)} categories")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        document = {
            "protocol": "scan",
            "scans": args.scans,
            "data": str(args.data),
            "split": args.split,
            "views": args.views,
            "categories": args.categories,
            "missing_ratio": args.ratio,
            "up": args.up,
            "seed": args.seed,
            "turned": not args.no_turn,
            "checkpoint": args.checkpoint or "default shipped model",
            "mirror_fill": DEFAULT_MIRROR_FILL if args.mirror_fill is None else args.mirror_fill,
            "complete_said": said,
            "complete_seconds": round(elapsed, 2),
            "f_wins_over_mirror": wins,
            "results": tables,
        }
        args.json.write_text(json.dumps(document, indent=2) + "\n")


if __name__ == "__main__":
    main()
