"""The README and the documentation pages: what they promise a newcomer holds.

The figures the pages publish are pinned to their records elsewhere (test_reproduce,
test_converged_study, test_small_data_runs); these tests check the shape of the guide.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from pfnet.cli import main

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
README = ROOT / "README.md"


def test_the_readme_is_short_and_starts_with_the_two_set_up_commands():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 250
    first_block = lines[lines.index("```bash") + 1 : lines.index("```")]
    assert lines.index("```bash") < 5  # right under the title
    assert [line.split("#")[0].strip() for line in first_block] == [
        'pip install -e ".[train]" && pfnet demo',
        'pip install -e ".[train,test]" && python -m pytest -q',
    ]


def test_every_link_of_the_readme_into_the_repository_exists():
    text = README.read_text(encoding="utf-8")
    targets = {t.split("#")[0] for t in re.findall(r"\]\(([^)]+)\)", text)}
    local = {t for t in targets if not t.startswith(("http://", "https://")) and t}
    assert {t for t in local if not (ROOT / t).exists()} == set()
    assert {"docs/index.md", "docs/getting-started.md", "docs/reference.md"} <= local


def test_every_page_is_in_the_site_and_every_entry_is_a_page():
    """mkdocs --strict refuses a nav entry whose file is missing; a page left out of the nav
    would be built but unreachable."""
    config = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    nav = set(re.findall(r"^\s*- (?:[^:]+: )?\"?([\w./-]+\.md)\"?\s*$", config, re.M))
    nav |= set(re.findall(r":\s*([\w./-]+\.md)\s*$", config, re.M))
    pages = {str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md")}
    assert len(pages) >= 8
    assert nav - pages == set()
    assert pages - nav == set()


def test_no_run_logs_or_records_under_docs():
    """Records of experiments live in results/; docs/ holds pages and the pictures they show."""
    kinds = {p.suffix for p in DOCS.rglob("*") if p.is_file()}
    assert kinds <= {".md", ".png", ".svg"}


def test_no_hint_names_the_pypi_project_that_is_not_pfnet():
    """'pfnet' on PyPI is an unrelated power-flow library: a hint `pip install 'pfnet[...]'`
    would fetch it. The distribution is pfnet-completion."""
    bad = re.compile(r"pip install\s+['\"]?pfnet(\[|\s|['\"]|$)")
    files = [README, *DOCS.rglob("*.md"), *(ROOT / "python" / "pfnet").rglob("*.py")]
    hints = [
        f"{f.relative_to(ROOT)}: {line.strip()}"
        for f in files
        for line in f.read_text(encoding="utf-8").splitlines()
        if bad.search(line) and "would" not in line  # the pages that explain the name say so
    ]
    assert hints == []
    assert 'name = "pfnet-completion"' in (ROOT / "pyproject.toml").read_text()


def test_pfnet_models_and_the_model_card_agree_on_the_sizes(capsys):
    """The network takes the partial cloud (1,536 points of a 2,048-point cloud at 25 %
    missing) and gives the missing 512; `pfnet models` once said "2048 points in"."""
    pytest.importorskip("safetensors")
    assert main(["models"]) == 0
    out = capsys.readouterr().out
    network = next(line for line in out.splitlines() if line.strip().startswith("network"))
    assert "1,536 points in, the missing 512 out" in network
    card = (DOCS / "models.md").read_text(encoding="utf-8")
    assert "1,536 points in, the missing 512 (25 %) out" in card
    assert "1,536 points in, the missing 512 out" in README.read_text(encoding="utf-8")


def test_the_model_cards_page_is_generated_from_the_model_files():
    """docs/models.md's cards section is what benchmarks/model_cards.py makes of the shipped
    files' metadata (regenerate it with the script when a model changes)."""
    pytest.importorskip("safetensors")
    from scripts import load_script

    cards = load_script("model_cards")
    assert cards.page_section(DOCS / "models.md") == cards.section()
    assert "1,536 points in, the missing 512 out" in cards.section()
