"""Train and score single runs of the study by name, exactly as ``pfnet reproduce`` does.

    python benchmarks/study_run.py pfnet-50-10000steps-seed0 mlp-25-20000steps-seed0 \
        --out study-runs --data data/sh3d --train-data data/sh3d-all

``pfnet reproduce`` trains every setting of its models at every length, and always the 25 %
ablation; a published study whose twice-the-steps test still needs a few longer runs (issue
#13's item 7) is extended with this script instead: it trains only the named runs, with the
study's configuration (``pfnet.study.runs.study_config``, the same preset and overrides),
in OUT/<name>/ (interrupted: run it again and it resumes), scores the test split with
``best.pt`` (``evaluate_run``) and writes the run's record to OUT/<name>/record.json. The
files a study publishes of a run are config.json, log.jsonl, eval-missing.json and
eval-whole.json.

``--config KEYS.toml`` trains with those keys over the preset instead of the study's
configuration (the name still sets the model, ratio, seed and length): a published run's
``config.json`` made a TOML file extends that run to another length with everything else
as it trained, keys added to pfnet since then included (``batchnorm_freeze = 0.0``,
``lr_decay = "step"`` for runs from before those keys).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from pfnet.models.registry import MODEL_NAMES
from pfnet.study.runs import STUDY_SCHEDULES, StudyRun, evaluate_run, study_config, train_run

RUN_NAME = re.compile(
    r"(?P<model>[a-z-]+)-(?P<ratio>\d{1,2})-(?P<steps>\d+)steps-seed(?P<seed>\d+)"
)


def parse_run(name: str) -> StudyRun:
    """The study run called ``name`` (e.g. ``mr-cmlp-25-20000steps-seed0``)."""
    match = RUN_NAME.fullmatch(name)
    if match is None or match["model"] not in MODEL_NAMES or not 0 < int(match["ratio"]) < 100:
        raise SystemExit(
            f"study_run.py: {name!r} is not a study run name such as pfnet-50-10000steps-seed0 "
            f"(models: {', '.join(MODEL_NAMES)})"
        )
    run = StudyRun(
        match["model"], int(match["ratio"]) / 100, int(match["seed"]), int(match["steps"])
    )
    assert run.name == name, (run.name, name)
    return run


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="run names, e.g. pfnet-50-10000steps-seed0")
    parser.add_argument("--out", type=Path, required=True, help="folder of the run folders")
    parser.add_argument("--data", type=Path, required=True, help="the study's data set")
    parser.add_argument("--train-data", type=Path, help="train on this data set's train split")
    parser.add_argument("--preset", default="small", choices=tuple(STUDY_SCHEDULES))
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    parser.add_argument(
        "--config", type=Path, help="TOML file of keys over the preset (default: the study's)"
    )
    args = parser.parse_args(argv)
    runs = [parse_run(name) for name in args.runs]  # every name checked before any training
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    if args.config:
        from pfnet.training.config import load_config

        base = load_config(args.config, preset=args.preset)
    else:
        base = study_config(args.preset)
    for run in runs:
        run_dir = args.out / run.name
        try:
            train_run(run, base, args.data, run_dir, args.device, print, args.train_data)
        except KeyboardInterrupt:
            print(f"{run.name}: stopped; run the same command again to resume", file=sys.stderr)
            return 130
        record = evaluate_run(run, args.data, run_dir, args.device)
        (run_dir / "record.json").write_text(json.dumps(record, indent=1) + "\n")
        missing = record["missing"]["mean"]
        print(
            f"{run.name}: best val CD-L2 {record['best_val_cd_l2']:.3f} (epoch "
            f"{record['best_epoch']} of {record['epochs']}); test missing Pred→GT "
            f"{missing['pred_to_gt']:.3f} GT→Pred {missing['gt_to_pred']:.3f} (×1000)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
