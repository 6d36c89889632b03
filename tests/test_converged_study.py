"""benchmarks/converged_study.py: the study at the lengths the twice-the-steps rule accepts."""

from __future__ import annotations

from pathlib import Path

import pytest
from scripts import load_script

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def converged_study():
    return load_script("converged_study")


def _setting(model: str, steps: int, val: float) -> dict:
    return {
        "name": f"{model}-{steps}",
        "model": model,
        "missing_ratio": 0.25,
        "steps": steps,
        "best_val_cd_l2": val,
    }


def test_the_first_length_whose_twice_is_no_better_is_chosen(converged_study):
    settings = [
        _setting("mlp", 2500, 10.0),
        _setting("mlp", 5000, 9.0),  # 10 % better: 2,500 not converged
        _setting("mlp", 10000, 8.9),  # 1.1 % better: converged at 5,000
        _setting("mlp", 20000, 8.0),  # better again, but the rule took the first
        _setting("cmlp", 2500, 10.0),
        _setting("cmlp", 5000, 9.0),  # still improving at its longest pair
    ]
    mlp, cmlp = converged_study.converged(settings)
    assert (mlp["lengths"][mlp["at"]]["steps"], mlp["is_converged"]) == (5000, True)
    assert (cmlp["lengths"][cmlp["at"]]["steps"], cmlp["is_converged"]) == (5000, False)


def test_readme_section_is_the_scripts_output(converged_study):
    """The results page's section between the markers is what the published records give."""
    assert converged_study.readme_section(ROOT / "docs" / "results.md") == converged_study.section()


def test_a_readme_without_the_markers_is_refused_by_name(converged_study, tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text("# no section\n")
    with pytest.raises(SystemExit, match="README.md: no section between"):
        converged_study.update_readme(readme, "text\n")
    assert readme.read_text() == "# no section\n"
