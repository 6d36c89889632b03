"""The paper's comparisons re-run end to end on one data set (``pfnet reproduce``).

* :mod:`~pfnet.study.runs` — which runs a study has, their configurations, training and
  scoring one run;
* :mod:`~pfnet.study.aggregate` — the runs of a setting combined over seeds;
* :mod:`~pfnet.study.paper` — the paper's published numbers;
* :mod:`~pfnet.study.figures` — validation curves and the gallery of every model;
* :mod:`~pfnet.study.report` — the Markdown report, the README section, publishing;
* :mod:`~pfnet.study.record` — ``results.json`` read back and checked whole;
* :mod:`~pfnet.study.orchestrate` — a whole study, resumable.
"""

from pfnet.study.aggregate import summarize_settings
from pfnet.study.orchestrate import reproduce, write_results
from pfnet.study.report import (
    README_BEGIN,
    README_END,
    claims_table,
    publish,
    readme_section,
    region_table,
    render_report,
    update_readme,
)
from pfnet.study.runs import (
    BASE_RATIO,
    STUDY_MODELS,
    STUDY_RATIOS,
    STUDY_SEEDS,
    StudyRun,
    plateau,
    study_runs,
)

__all__ = [
    "BASE_RATIO",
    "README_BEGIN",
    "README_END",
    "STUDY_MODELS",
    "STUDY_RATIOS",
    "STUDY_SEEDS",
    "StudyRun",
    "claims_table",
    "plateau",
    "publish",
    "readme_section",
    "region_table",
    "render_report",
    "reproduce",
    "study_runs",
    "summarize_settings",
    "update_readme",
    "write_results",
]
