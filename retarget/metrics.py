"""Evaluation protocol (paper Sec. IV-A): score any G1 reference against its demonstration.

Public API (implementation in ``retarget.evaluation``, one concept per module):

- ``evaluate_sequence(reference, demonstration, EvalConfig()) -> SequenceResult``: every metric
  of one reference — sc, rot, self, ground dd/dw/R/P/J, skate, clear, object dd/dw/R/P/J,
  drift — with the per-frame samples behind them; ``SequenceResult.as_dict()`` for JSON.
- ``dataset_medians(list of metric dicts)``: the per-dataset medians of the paper's tables.
- ``format_table(records)``: the paper's Tables I–III layout; ``plot_contact_timeline``,
  ``plot_metric_distributions``: PNG figures.
- ``configure_parser`` / ``main``: the ``otr eval`` command.

Metrics are stored in SI units and fractions (``ground_dd_m``, ``object_recall``, …); the
table converts to the paper's mm, %, cm/s, cm.
"""

from retarget.evaluation.cli import configure_parser, main
from retarget.evaluation.config import EvalConfig
from retarget.evaluation.plots import plot_contact_timeline, plot_metric_distributions
from retarget.evaluation.report import format_table
from retarget.evaluation.scale import ScaleFit
from retarget.evaluation.sequence import TABLE_COLUMNS, SequenceResult, dataset_medians, evaluate_sequence
from retarget.evaluation.units import BodyUnit, default_units

__all__ = [
    "TABLE_COLUMNS", "BodyUnit", "EvalConfig", "ScaleFit", "SequenceResult", "configure_parser", "dataset_medians",
    "default_units", "evaluate_sequence", "format_table", "main", "plot_contact_timeline",
    "plot_metric_distributions",
]
