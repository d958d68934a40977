"""The evaluation protocol (paper Sec. IV-A, ``docs/evaluation.md``): score any G1 reference
against its demonstration, whoever made the reference. Solver-independent: the retargeter's
solver reads two of its definitions (body units, the least-moving foot speed), never the
other way round.

Public API (one concept per module, loaded on first use so that importing one module of this
package does not load the others):

- ``evaluate_sequence(reference, demonstration, EvalConfig()) -> SequenceResult``: every metric
  of one reference — sc, rot, self, ground dd/dw/R/P/J, skate, clear, object dd/dw/R/P/J,
  drift — with the per-frame samples behind them; ``SequenceResult.as_dict()`` for JSON.
- ``dataset_medians(list of metric dicts)``: the per-dataset medians of the paper's tables.
- ``format_table(records)``: the paper's Tables I–III layout; ``plot_contact_timeline``,
  ``plot_metric_distributions``: PNG figures.

Metrics are stored in SI units and fractions (``ground_dd_m``, ``object_recall``, …); the
table converts to the paper's mm, %, cm/s, cm. The command is ``otr score``
(``retarget.cli.score``).
"""

from __future__ import annotations

import importlib

_PUBLIC = {
    "EvalConfig": "config", "plot_contact_timeline": "plots", "plot_metric_distributions": "plots",
    "format_table": "report", "ScaleFit": "scale", "TABLE_COLUMNS": "sequence", "SequenceResult": "sequence",
    "dataset_medians": "sequence", "evaluate_sequence": "sequence", "BodyUnit": "units", "default_units": "units",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module 'retarget.evaluation' has no attribute {name!r}")
    return getattr(importlib.import_module(f"retarget.evaluation.{_PUBLIC[name]}"), name)
