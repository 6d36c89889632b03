"""The study's section of the documentation page ``docs/results.md``, from its record.

    python benchmarks/study_page.py            # rewrite the section between its markers

``pfnet reproduce --publish results/study`` copies the study's small files (``results.json``,
the runs' logs and scores, ``curves.png`` and ``gallery.png``) into the record folder
``results/study/``. The documentation shows the two pictures beside its page, so this script
moves them to ``docs/results/`` when the record has new ones, and rewrites the page's section
from ``results.json`` with the pictures linked there; a test checks the section is this output.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from pfnet.study import render_report, update_readme

ROOT = Path(__file__).resolve().parent.parent
RECORD = ROOT / "results" / "study"
PAGE = ROOT / "docs" / "results.md"
PICTURES = ("curves.png", "gallery.png")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--record", type=Path, default=RECORD, help="the published study")
    parser.add_argument("--page", type=Path, default=PAGE, help="the page with the markers")
    args = parser.parse_args(argv)
    pictures = args.page.parent / args.page.stem  # docs/results/ beside docs/results.md
    for name in PICTURES:
        if (args.record / name).is_file():
            pictures.mkdir(exist_ok=True)
            shutil.move(args.record / name, pictures / name)
    results = json.loads((args.record / "results.json").read_text(encoding="utf-8"))
    update_readme(args.page, render_report(results, f"{args.page.stem}/"))
    print(f"updated the results section of {args.page}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
