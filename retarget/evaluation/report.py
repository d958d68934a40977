"""Reports of an evaluation: the paper-style table (Tables I–III) and the JSON record.

Both work from the JSON-ready records (``SequenceResult.as_dict``), so a resumed evaluation
reports sequences scored in an earlier run exactly like fresh ones.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from retarget.evaluation.sequence import TABLE_COLUMNS, dataset_medians

#: Column groups of the table: (title, first column key, last column key).
_GROUPS = (("Ground", "ground_dd_m", "clear_m"), ("Object", "object_dd_m", "drift_m"))


def _cell(value, factor: float, digits: int) -> str:
    if value is None or not math.isfinite(value):
        return "–"
    return f"{value * factor:.{digits}f}"


def format_table(records: list[dict], medians: bool | None = None) -> str:
    """Rows = sequences (and their median when there are several demonstrations), columns =
    the paper's metrics: sc, rot, self | ground dd R P J skate clear | object dd dw R P J drift."""
    names = [r["name"] for r in records]
    rows = [[r["name"]] + [_cell(r["metrics"].get(k), f, dg) for k, _, _, f, dg in TABLE_COLUMNS] for r in records]
    if medians is None:
        medians = len({r["demonstration"] for r in records}) > 1
    if medians:
        med = dataset_medians([r["metrics"] for r in records])
        rows.append([f"median ({len(records)} sequences)"]
                    + [_cell(med.get(k), f, dg) for k, _, _, f, dg in TABLE_COLUMNS])
    header = ["Reference"] + [h for _, h, _, _, _ in TABLE_COLUMNS]
    units = [""] + [u for _, _, u, _, _ in TABLE_COLUMNS]
    width = [max(len(x) for x in col) for col in zip(header, units, *rows)]
    width[0] = max(width[0], max((len(n) for n in names), default=0))
    keys = [None] + [k for k, _, _, _, _ in TABLE_COLUMNS]

    def line(cells):
        out = []
        for i, (c, wd) in enumerate(zip(cells, width)):
            sep = " | " if keys[i] in {g[1] for g in _GROUPS} else " "
            out.append((sep if i else "") + (c.ljust(wd) if i == 0 else c.rjust(wd)))
        return "".join(out)

    title = [""] * len(header)
    for name, first, _ in _GROUPS:
        title[keys.index(first)] = name
    lines = [line(title), line(header), line(units), "-" * len(line(header))]
    lines += [line(r) for r in rows]
    return "\n".join(lines)


def format_scale_notes(records: list[dict]) -> str:
    """One line per sequence: the scale used and how well the trajectory fit supports it."""
    out = []
    for r in records:
        s = r["scale"]
        fit = "fit unavailable" if s["fit_sc"] is None else (
            f"fit {s['fit_sc']:.4f}, rms {s['fit_rms_m'] * 1000:.1f} mm, R² {s['fit_r2']:.4f}")
        out.append(f"{r['name']}: sc {s['sc']:.4f} ({s['source']}; {fit}; robot height / stature "
                   f"{s['stature_sc']:.4f})")
    return "\n".join(out)


def format_object_notes(records: list[dict]) -> str:
    """For sequences with several objects, one line each: the robot's scores per object channel
    and the objects' own contacts (box–table, box–ground). Empty when every sequence has one."""
    def scores(s: dict) -> str:
        if not s["n_h"] and not s["n_r"]:
            return "no contact in either"
        return (f"R {_cell(s['recall'], 100.0, 0)} % P {_cell(s['precision'], 100.0, 0)} % "
                f"dd {_cell(s['dd_m'], 1e3, 1)} mm (H {s['n_h']}, R {s['n_r']})")

    out = []
    for r in records:
        details = r.get("details", {})
        channels, pairs = details.get("object_channels", {}), details.get("object_pairs", {})
        if len(channels) < 2:
            continue
        parts = [f"robot–{name} {scores(s)}" for name, s in channels.items()]
        parts += [f"{name.replace('|', '–')} {scores(s)}" for name, s in pairs.items()]
        out.append(f"{r['name']}: " + "; ".join(parts))
    return "\n".join(out)


def read_json(path: str | Path) -> dict:
    """An earlier evaluation record; a corrupt file raises ValueError naming it."""
    path = Path(path)
    try:
        with path.open(encoding="utf-8") as f:
            data = json.load(f)
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable evaluation JSON ({exc})") from exc
    sequences = data.get("sequences") if isinstance(data, dict) else None
    if not isinstance(sequences, list):  # a bad file, not a bad argument: ValueError like the rest
        raise ValueError(f"{path}: not an evaluation JSON (no 'sequences' list)")  # noqa: TRY004
    return data
