"""``pfnet evaluate``: score any method's prediction folder against a data set.

The scoring (file layout, regions, metrics, the protocol ``PRED/predictions.json`` records)
is :mod:`pfnet.evaluation.scoring`'s; this module holds the command: its options, the checks of its
output paths and of the recorded protocol against the options, and what it prints.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from pfnet.data.format import read_manifest
from pfnet.errors import ConfigError, DataError
from pfnet.evaluation.benchmarks import evaluate_benchmark, evaluate_kitti
from pfnet.evaluation.prediction_record import (
    recorded_data_problem,
    recorded_protocol,
    recorded_protocol_name,
)
from pfnet.evaluation.protocols import Protocol
from pfnet.evaluation.scoring import (
    FAR,
    MAX_WORKERS,
    REGIONS,
    SCALE,
    Evaluation,
    evaluate_predictions,
)
from pfnet.viz.gallery import render_evaluation_gallery

HELP = "Score a folder of predicted point clouds against a data set (Chamfer ×1000, F-score)."
PROTOCOL_NAMES = ("pfnet", "pcn", "shapenet55", "shapenet34", "kitti")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``pfnet evaluate``."""
    parser.add_argument("pred", type=Path, help="prediction folder PRED/<category>/<name>.<ext>")
    parser.add_argument("--data", type=Path, required=True, help="prepared data set folder")
    parser.add_argument("--split", default="test", help="split to score (default: test)")
    parser.add_argument(
        "--missing-ratio",
        type=float,
        default=None,
        help="fraction of points the test protocol removes (default: the one recorded in "
        "PRED/predictions.json, else 0.25)",
    )
    parser.add_argument(
        "--ignore-recorded-protocol",
        action="store_true",
        help="score even if --split/--missing-ratio differ from PRED/predictions.json",
    )
    parser.add_argument(
        "--protocol",
        choices=PROTOCOL_NAMES,
        default=None,
        help="pfnet: PF-Net's crop, missing region, squared CD ×1000; pcn, shapenet55 "
        "(= shapenet34): whole completions scored as PoinTr does (CD-L1/CD-L2 ×1000, "
        "F-score@0.01); kitti: Fidelity and MMD ×1000 against --references "
        "(default: the one recorded in PRED/predictions.json, else pfnet)",
    )
    parser.add_argument(
        "--references",
        type=Path,
        default=None,
        metavar="CARS",
        help="kitti protocol: a prepared data set whose --reference-category clouds, all "
        "splits, are the reference cars of MMD (PoinTr: PCN's cars)",
    )
    parser.add_argument(
        "--reference-category",
        default=None,
        help="kitti protocol: the category of the reference cars (default: car)",
    )
    parser.add_argument(
        "--region",
        choices=REGIONS,
        default=None,
        help="pfnet protocol: region scored (default: missing)",
    )
    parser.add_argument(
        "--pred-is-complete",
        action="store_true",
        help="with --region whole: files hold full completions, not the missing region",
    )
    parser.add_argument("--json", type=Path, default=None, help="write the summary as JSON")
    parser.add_argument("--csv", type=Path, default=None, help="write per-sample scores as CSV")
    parser.add_argument(
        "--allow-missing",
        action="store_true",
        help="exit 0 even if some prediction files are missing or unreadable",
    )
    parser.add_argument(
        "--gallery",
        type=Path,
        default=None,
        help="render samples into a PNG (or, .html, an interactive viewer)",
    )
    parser.add_argument(
        "--gallery-count", type=int, default=None, help="samples in the gallery (default: 8)"
    )
    parser.add_argument("--workers", type=int, default=None, help="file-reading threads")


def run(args: argparse.Namespace) -> int:
    """Run ``pfnet evaluate``; exit 2 if files were missing/unreadable (unless allowed).

    The prediction folder and the data set are held (shared locks, :mod:`pfnet.io.locks`)
    while they are read: a ``predict`` or ``prepare`` rewriting them meanwhile is refused,
    never scored as a mix of two runs.
    """
    from pfnet.io.locks import reading

    with reading(args.pred, "scoring"), reading(args.data, "reading"):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from pfnet.evaluation.metrics import summarize
    from pfnet.evaluation.reports import format_table, write_csv
    from pfnet.io.files import check_report_path
    from pfnet.viz.gallery import check_gallery_options

    args.gallery_count = check_gallery_options(args.gallery, args.gallery_count)
    given = [Path(p).resolve() for p in (args.json, args.csv, args.gallery) if p is not None]
    if len(set(given)) < len(given):
        raise ConfigError("--json, --csv and --gallery name the same file; name one for each")
    protocol = _scoring_protocol(args)
    if protocol != "pfnet":
        return _run_benchmark(args, protocol)
    for flag, value in (
        ("--references", args.references),
        ("--reference-category", args.reference_category),
    ):
        if value is not None:
            raise ConfigError(f"{flag} applies to the kitti protocol, not to pfnet")
    args.region = args.region or "missing"
    if args.pred_is_complete and args.region != "whole":
        raise ConfigError("--pred-is-complete needs --region whole")
    if args.workers is not None and not 1 <= args.workers <= MAX_WORKERS:
        raise ConfigError(f"--workers must be in [1, {MAX_WORKERS}], got {args.workers}")
    args.missing_ratio = _scoring_ratio(args)
    if not 0.0 < args.missing_ratio < 1.0:
        raise ConfigError(f"--missing-ratio must be in (0, 1), got {args.missing_ratio}")
    for flag in ("json", "csv", "gallery"):
        if getattr(args, flag) is not None:  # checked before scoring, not after
            check_report_path(getattr(args, flag), args.pred, [args.data], flag=f"--{flag}")
    evaluation = evaluate_predictions(
        args.pred,
        args.data,
        split=args.split,
        missing_ratio=args.missing_ratio,
        region=args.region,
        pred_is_complete=args.pred_is_complete,
        workers=args.workers,
        notes=_say_skipped,
    )
    summary = summarize(evaluation.per_sample, evaluation.categories, scale=float(SCALE))
    n_scored = len(evaluation.categories)
    print(
        f"{args.pred} vs {args.data} [{args.split}]: region {args.region}, "
        f"{args.missing_ratio:.0%} missing, {n_scored} of {evaluation.n_samples} samples scored"
    )
    print("Pred→GT, GT→Pred, CD-L2, CD-L1 ×1000; F-score at distance 0.01")
    print(format_table(evaluation, summary))
    _write_reports(args, evaluation, write_csv)
    if args.gallery is not None:
        path = render_evaluation_gallery(
            args.gallery,
            evaluation,
            args.pred,
            args.data,
            split=args.split,
            missing_ratio=args.missing_ratio,
            count=args.gallery_count,
        )
        print(f"wrote {path}")
    return _exit_code(args, evaluation)


def _scoring_protocol(args: argparse.Namespace) -> str:
    """``--protocol``, else the one PRED/predictions.json records, else ``pfnet``; a
    ``--protocol`` that differs from the record is refused."""
    from pfnet.evaluation.protocols import get_protocol

    try:
        recorded = recorded_protocol_name(args.pred)
    except DataError:
        recorded = None  # _scoring_ratio reports the unreadable record
    asked = None if args.protocol is None else get_protocol(args.protocol).name
    if asked is None:
        return recorded or "pfnet"
    if recorded is not None and recorded != asked and not args.ignore_recorded_protocol:
        raise ConfigError(
            f"{args.pred} holds predictions made with the {recorded} protocol "
            f"({Path(args.pred) / 'predictions.json'}); pass --protocol {recorded}, or "
            "--ignore-recorded-protocol"
        )
    return asked


def _run_benchmark(args: argparse.Namespace, protocol: str) -> int:
    """``pfnet evaluate --protocol pcn|shapenet55|kitti``: whole completions scored as PoinTr
    does."""
    from pfnet.evaluation.protocols import get_protocol
    from pfnet.evaluation.reports import format_benchmark_table, write_csv
    from pfnet.io.files import check_report_path

    chosen = get_protocol(protocol)
    for flag, value in (
        ("--region", args.region),
        ("--pred-is-complete", args.pred_is_complete or None),
    ):
        if value is not None:
            raise ConfigError(f"{flag} applies to the pfnet protocol, not to {protocol}")
    if protocol == "kitti" and args.references is None:
        raise ConfigError(
            "the kitti protocol needs --references CARS: a prepared data set holding complete "
            "car clouds (e.g. PCN prepared with --categories car) to measure MMD against"
        )
    for flag, value in (
        ("--references", args.references),
        ("--reference-category", args.reference_category),
    ):
        if protocol != "kitti" and value is not None:
            raise ConfigError(f"{flag} applies to the kitti protocol, not to {protocol}")
    args.reference_category = args.reference_category or "car"
    if args.workers is not None and not 1 <= args.workers <= MAX_WORKERS:
        raise ConfigError(f"--workers must be in [1, {MAX_WORKERS}], got {args.workers}")
    ratio = args.missing_ratio
    if not chosen.ratios and ratio is not None:
        raise ConfigError(f"--missing-ratio does not apply to the {protocol} protocol")
    _check_benchmark_ratio(chosen, ratio)
    try:
        recorded = recorded_protocol(args.pred)
    except DataError as err:
        if not args.ignore_recorded_protocol:
            raise ConfigError(
                f"{err}; fix or remove it, or pass --ignore-recorded-protocol"
            ) from None
        recorded = None
    if recorded is not None and not args.ignore_recorded_protocol:
        made_split, made_ratio, _ = recorded
        if made_split != args.split:
            raise ConfigError(
                f"{args.pred} holds predictions of the {made_split!r} split; pass --split "
                f"{made_split}, or --ignore-recorded-protocol"
            )
        if chosen.ratios:
            if ratio is not None and not abs(ratio - made_ratio) <= 1e-9:
                raise ConfigError(
                    f"{args.pred} was predicted with {made_ratio:g} missing, not {ratio:g}; "
                    "drop --missing-ratio, or pass --ignore-recorded-protocol"
                )
            ratio = made_ratio
        _check_recorded_data(args)
    inputs = [args.data] if args.references is None else [args.data, args.references]
    for flag in ("json", "csv", "gallery"):
        if getattr(args, flag) is not None:
            check_report_path(getattr(args, flag), args.pred, inputs, flag=f"--{flag}")
    if protocol == "kitti":
        return _run_kitti(args)
    evaluation = evaluate_benchmark(
        args.pred,
        args.data,
        protocol,
        split=args.split,
        missing_ratio=ratio,
        workers=args.workers,
        notes=_say_skipped,
    )
    report = evaluation.report
    shown = "" if report["missing_ratio"] is None else f", {report['missing_ratio']:.0%} missing"
    print(
        f"{args.pred} vs {args.data} [{args.split}]: protocol {protocol}{shown}, "
        f"{len(evaluation.categories)} of {evaluation.n_samples} completions scored"
    )
    print(f"{chosen.title}; CD-L1, CD-L2, Pred→GT, GT→Pred ×1000 (PoinTr's), F-score at 0.01")
    print(format_benchmark_table(report))
    _write_reports(args, evaluation, write_csv)
    _benchmark_gallery(args, evaluation, protocol, report["missing_ratio"])
    return _exit_code(args, evaluation)


def _run_kitti(args: argparse.Namespace) -> int:
    """``pfnet evaluate --protocol kitti``: Fidelity and MMD of the completions of the cars."""
    from pfnet.evaluation.reports import format_kitti_table, write_kitti_csv

    evaluation = evaluate_kitti(
        args.pred,
        args.data,
        args.references,
        reference_category=args.reference_category,
        split=args.split,
        workers=args.workers,
        notes=_say_skipped,
    )
    report = evaluation.report
    print(
        f"{args.pred} vs {args.data} [{args.split}]: protocol kitti, "
        f"{len(evaluation.categories)} of {evaluation.n_samples} completions scored against "
        f"{report['references']['n']} reference cars of {args.references}"
    )
    print(
        "Fidelity (input → completion) and MMD (completion → nearest reference, CD-L2), "
        "×1000 (PoinTr's KITTI_metric.py)"
    )
    print(format_kitti_table(report))
    _write_reports(args, evaluation, write_kitti_csv)
    _benchmark_gallery(args, evaluation, "kitti", None)
    return _exit_code(args, evaluation)


def _benchmark_gallery(
    args: argparse.Namespace, evaluation: Evaluation, protocol: str, ratio: float | None
) -> None:
    """``--gallery`` of a benchmark protocol: scored completions, spread over the categories."""
    if args.gallery is None:
        return
    from pfnet.viz.gallery import render_benchmark_gallery

    keys = [f"{c}/{n}" for c, n in zip(evaluation.categories, evaluation.names, strict=True)]
    nearest = evaluation.labels.get("nearest_reference") if evaluation.labels else None
    path = render_benchmark_gallery(
        args.gallery,
        args.pred,
        args.data,
        protocol,
        keys=keys,
        count=args.gallery_count,
        split=args.split,
        missing_ratio=ratio,
        nearest=None if nearest is None else dict(zip(keys, nearest, strict=True)),
        references=args.references,
        reference_category=args.reference_category,
    )
    print(f"wrote {path}")


def _scoring_ratio(args: argparse.Namespace) -> float:
    """The missing ratio to score with, checked against ``PRED/predictions.json`` if present.

    Raises:
        ConfigError: ``--split`` or ``--missing-ratio`` differs from the record (unless
            ``--ignore-recorded-protocol``), or the record cannot be read.
    """
    record = Path(args.pred) / "predictions.json"
    asked = args.missing_ratio
    try:
        recorded = recorded_protocol(args.pred)
    except DataError as err:
        if args.ignore_recorded_protocol:
            return 0.25 if asked is None else asked
        raise ConfigError(f"{err}; fix or remove it, or pass --ignore-recorded-protocol") from None
    if recorded is None:
        return 0.25 if asked is None else asked
    made_split, made_ratio, made_points = recorded
    if made_ratio is None:  # a pcn record scored with the pfnet protocol
        return 0.25 if asked is None else asked
    ratio = made_ratio if asked is None else asked
    if args.ignore_recorded_protocol:
        return ratio
    if getattr(args, "pred_is_complete", False):
        raise ConfigError(
            f"{args.pred} holds predictions of the missing region only ({record} records the "
            "pfnet protocol, which writes that region): drop --pred-is-complete, or pass "
            "--ignore-recorded-protocol"
        )
    points = read_manifest(args.data).get("points")
    if made_points is not None and isinstance(points, int) and points != made_points:
        raise ConfigError(
            f"{args.pred} was predicted from clouds of {made_points} points ({record}); "
            f"--data {args.data} has {points}: score it against the data set it was "
            "predicted on, or pass --ignore-recorded-protocol"
        )
    if made_split != args.split:
        raise ConfigError(
            f"{args.pred} holds predictions of the {made_split!r} split "
            f"({record}); pass --split {made_split}, or --ignore-recorded-protocol"
        )
    if abs(ratio - made_ratio) > 1e-9:
        raise ConfigError(
            f"{args.pred} was predicted with {made_ratio:g} missing ({record}), "
            f"not {ratio:g}; drop --missing-ratio, or pass --ignore-recorded-protocol"
        )
    _check_recorded_data(args)
    return ratio


def _check_recorded_data(args: argparse.Namespace) -> None:
    """Refuse predictions recorded as made from other clouds than ``--data``'s split (the same
    names over other clouds were scored silently), unless ``--ignore-recorded-protocol``."""
    if args.ignore_recorded_protocol or not (Path(args.data) / f"{args.split}.npz").is_file():
        return  # a data set without the split is named by the scoring itself
    problem = recorded_data_problem(args.pred, args.data, args.split)
    if problem is not None:
        raise ConfigError(problem)


def _write_reports(args: argparse.Namespace, evaluation: Any, write_csv: Any) -> None:
    """``--json`` (the evaluation's report) and ``--csv`` (written by ``write_csv``)."""
    from pfnet.evaluation.reports import write_json

    for path in (args.json, args.csv):  # as galleries do: the scoring is not lost to a folder
        if path is not None:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
    if args.json is not None:
        write_json(args.json, evaluation.report)
        print(f"wrote {args.json}")
    if args.csv is not None:
        write_csv(args.csv, evaluation)
        print(f"wrote {args.csv}")


def _exit_code(args: argparse.Namespace, evaluation: Any) -> int:
    """0, or 2 when samples were not scored and ``--allow-missing`` was not given."""
    problems = _report_problems(evaluation)
    if problems and not args.allow_missing:
        print(
            "pfnet evaluate: some samples were not scored (pass --allow-missing to accept)",
            file=sys.stderr,
        )
        return 2
    return 0


def _report_problems(evaluation: Evaluation, limit: int = 20) -> bool:
    """Print missing, unreadable and unmatched files to stderr; True if samples went unscored."""
    if evaluation.far:
        print(
            f"warning: {len(evaluation.far)} prediction(s) reach more than {FAR:g} from the "
            f"origin (e.g. {evaluation.far[0]}), where the data set's clouds lie within 1: "
            "are they in the data set's normalised coordinates?",
            file=sys.stderr,
        )
    if evaluation.unmatched:
        print(
            f"warning: {len(evaluation.unmatched)} prediction file(s) match no sample, "
            f"e.g. {evaluation.unmatched[0]}",
            file=sys.stderr,
        )
    if evaluation.missing:
        shown = ", ".join(evaluation.missing[:limit])
        more = (
            f" and {len(evaluation.missing) - limit} more"
            if len(evaluation.missing) > limit
            else ""
        )
        print(
            f"missing: {len(evaluation.missing)} sample(s) have no prediction file: {shown}{more}",
            file=sys.stderr,
        )
    for reason in evaluation.reasons[:limit]:
        print(f"unreadable: {reason}", file=sys.stderr)
    if len(evaluation.reasons) > limit:
        print(f"unreadable: and {len(evaluation.reasons) - limit} more", file=sys.stderr)
    return bool(evaluation.missing or evaluation.unreadable)


def _check_benchmark_ratio(chosen: Protocol, ratio: float | None) -> None:
    """Refuse a ``--missing-ratio`` that is not finite, not in (0, 1) or not the protocol's."""
    if ratio is None:
        return
    if not 0.0 < ratio < 1.0:  # also false for NaN
        raise ConfigError(f"--missing-ratio must be in (0, 1), got {ratio}")
    if chosen.ratios and not any(abs(ratio - r) <= 1e-9 for r in chosen.ratios):
        listed = ", ".join(f"{r:g}" for r in chosen.ratios)
        raise ConfigError(
            f"--missing-ratio of the {chosen.name} protocol is one of {listed}, got {ratio:g}"
        )


def _say_skipped(line: str) -> None:
    """A prediction folder's category folder that could not be listed, on stderr."""
    print(line, file=sys.stderr)
