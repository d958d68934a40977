"""``otr variants``' table (``retarget.cli.variants.format_variants_table``)."""

from __future__ import annotations

from retarget.cli.variants import format_variants_table


def record(label: str, shape: str, scale: float, retarget_s: float | None, job_s: float) -> dict:
    """A variant's record as ``run_variant`` writes it, with the numbers the table reads."""
    return {"label": label, "shape": shape, "scale": [scale] * 3, "warnings": [],
            "metrics": {"object_dd_m": 0.004, "object_recall": 0.9, "object_precision": 0.8, "object_jaccard": 0.7,
                        "drift_m": 0.01, "grip_recall": 0.95, "grip_precision": 0.85},
            "checks": {"robot_penetration_m": 1e-4, "object_in_robot_m": 0.0},
            "timing": {"retarget_s": retarget_s, "job_s": job_s}}


def cells(table: str, label: str) -> dict[str, str]:
    """Header -> cell of the row whose label starts with ``label``."""
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in table.splitlines()]
    header = rows[0]
    row = next(r for r in rows[2:] if r[0].startswith(label))
    return dict(zip(header, row, strict=True))


def test_the_table_shows_the_retarget_time_and_the_whole_jobs_time_each_labelled():
    table = format_variants_table([record("box ×1.0", "original", 1.0, 14.2, 75.4),
                                   record("ball ×1.0", "ball", 1.0, 23.0, 92.1)])
    native, ball = cells(table, "box ×1.0"), cells(table, "ball ×1.0")
    assert (native["retarget s"], native["job s"]) == ("14", "75")
    assert (ball["retarget s"], ball["job s"]) == ("23", "92")
    assert "time s" not in table


def test_a_variant_retargeted_in_an_earlier_run_shows_only_this_runs_job_time():
    row = cells(format_variants_table([record("box ×1.0", "original", 1.0, None, 6.0)]), "box ×1.0")
    assert (row["retarget s"], row["job s"]) == ("–", "6")
