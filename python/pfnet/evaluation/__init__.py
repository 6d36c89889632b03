"""Scoring predictions: the metrics (:mod:`~pfnet.evaluation.metrics`), the benchmarks'
protocols (:mod:`~pfnet.evaluation.protocols`), the prediction folder ``pfnet predict``
fills and its records (:mod:`~pfnet.evaluation.prediction_folder`,
:mod:`~pfnet.evaluation.prediction_record`), scoring a folder
(:mod:`~pfnet.evaluation.scoring`, :mod:`~pfnet.evaluation.benchmarks`) and the reports
(:mod:`~pfnet.evaluation.reports`)."""
