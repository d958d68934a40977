"""One demonstration, many references: ``otr variants`` (paper Sec. IV-D, Table IV, Fig. 5).

    otr variants DEMO [--object MESH] --shapes original,ball,torus,… --scales 0.7:1.6:0.1
                 [--workers N] --out DIR [--free table] [--config YAML] [--overwrite]

Every (shape, scale) pair is a variant: the demonstration with its manipulated object replaced
(``retarget.solver.substitute``) and retargeted (``retarget.clip``), then scored against the
*unchanged* demonstration with the paper's protocol (``retarget.evaluation``) and checked for
penetration on the robot's visual meshes (``retarget.checks.verify``). ``original`` is the captured
object itself (at ×1 the native retarget). Shapes: the library (``retarget.inputs.shapes``) or mesh
files (.obj/.stl/.ply, z up).

Outputs in DIR, each written atomically:

* ``<demo>__<variant>.npz``: the reference (it carries the substitute's mesh);
* ``<demo>__<variant>.json``: its record (metrics, checks, timings, warnings);
* ``variants.json`` (every record), ``variants.md`` (the Table-IV layout: dd, R, P, J, drift per
  variant, with the grip — the hands alone — recall and precision, penetration, and the time of
  the retarget alone — problem set-up and solve — and of the variant's whole job — substitution,
  retarget and scoring, ``job_s`` in its record),
  ``recall_precision_vs_scale.png`` (Fig. 5: grip recall and precision against the scale).

The batch is the retarget batch (``retarget.cli.executors.run_batch``): progress bar, ``--workers``
processes, resumable (a variant whose record exists is skipped; one whose reference exists is
only scored again), a failing variant is reported and the batch goes on (exit code 1). A
variant whose hands reach the object in fewer than ``--min-recall`` of the demonstrated grip
samples (a substitute too big for the G1's reach) finishes with a warning and its recall.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from otr_gym.io import atomic_path, save_figure, write_json
from retarget.cli.executors import run_batch
from retarget.config import ConfigError, RetargetConfig, load_config
from retarget.inputs.shapes import (
    ORIGINAL,
    SHAPE_NAMES,
    ShapeSpec,
    UnknownShapeError,
    load_shape_mesh,
    parse_scales,
    parse_shapes,
)
from retarget.solver.substitute import SubstitutionConfig

#: Columns of the variants table: record key path, header, unit, factor, digits.
TABLE_COLUMNS = (
    (("metrics", "object_dd_m"), "dd", "mm", 1e3, 1),
    (("metrics", "object_recall"), "R", "%", 100.0, 0),
    (("metrics", "object_precision"), "P", "%", 100.0, 0),
    (("metrics", "object_jaccard"), "J", "%", 100.0, 0),
    (("metrics", "drift_m"), "drift", "cm", 100.0, 1),
    (("metrics", "grip_recall"), "grip R", "%", 100.0, 0),
    (("metrics", "grip_precision"), "grip P", "%", 100.0, 0),
    (("checks", "robot_penetration_m"), "pen robot", "mm", 1e3, 2),
    (("checks", "object_in_robot_m"), "pen object", "mm", 1e3, 2),
    # the retarget alone (problem set-up + solve) and the variant's whole job (substitution, retarget, scoring)
    (("timing", "retarget_s"), "retarget", "s", 1.0, 0),
    (("timing", "job_s"), "job", "s", 1.0, 0),
)
#: Extra column when the scene has object–object contacts (the box on the table).
PAIR_COLUMN = (("metrics", "pair_recall"), "obj-obj R", "%", 100.0, 0)


@dataclass(frozen=True)
class VariantJob:
    """One variant of one demonstration and where its outputs go."""

    demo: Path
    object_mesh: Path | None
    spec: ShapeSpec
    output: Path  # the reference (.npz); its record is the same name with .json
    object_name: str | None = None
    free: tuple[str, ...] = ()

    @property
    def record(self) -> Path:
        return self.output.with_suffix(".json")


def variant_jobs(demo: Path, object_mesh: Path | None, shapes: list[str], scales: list[tuple[float, float, float]],
                 out: Path, object_name: str | None = None, free: tuple[str, ...] = (),
                 keep_frame: bool = False) -> list[VariantJob]:
    """Every (shape, scale) pair, in order; duplicate variants are made once."""
    jobs, seen = [], set()
    for shape in shapes:
        for scale in scales:
            spec = ShapeSpec(shape, scale, keep_frame=keep_frame)
            if spec.name in seen:
                continue
            seen.add(spec.name)
            jobs.append(VariantJob(Path(demo), object_mesh, spec, Path(out) / f"{Path(demo).stem}__{spec.name}.npz",
                                   object_name, tuple(free)))
    return jobs


@functools.lru_cache(maxsize=2)
def _demonstration(path: Path, object_mesh: Path | None):
    from retarget.inputs.readers import load_demonstration

    return load_demonstration(path, object_mesh)


def _variant_demo(job: VariantJob, cfg: SubstitutionConfig):
    from retarget.solver.substitute import free_objects, substitute

    demo = _demonstration(job.demo, job.object_mesh)
    if job.free:
        demo = free_objects(demo, job.free)
    return demo, substitute(demo, job.spec, job.object_name, cfg)


def grip_scores(result) -> dict[str, float]:
    """The paper's *grip* (Fig. 5): the object metrics restricted to the hand units (those
    holding a wrist-yaw link, the G1's fixed hand) against the manipulated objects."""
    from retarget.evaluation.contact import contact_scores

    links = result.details["unit_links"]
    hands = [k for k, u in enumerate(result.units) if any(lk.endswith("wrist_yaw_link") for lk in links[u])]
    moving = [c for c, o in enumerate(result.details["objects"], start=1) if not o["static"]]
    d_hat = result.d_hat_m[:, hands][:, :, moving]
    d = result.d_m[:, hands][:, :, moving]
    none = np.zeros(d.shape + (3,))
    s = contact_scores(d_hat, none, d, none, result.eps_m)
    return {"grip_dd_m": s.dd_m, "grip_recall": s.recall, "grip_precision": s.precision, "grip_jaccard": s.jaccard}


def measure_variant(reference, demo, made=None) -> dict:
    """Protocol metrics of a variant's reference against the original demonstration, the
    solver-independent checks (penetration both ways on the robot's visual meshes, hand hold)
    and, when this run made it (``made``: ``retarget.clip.Timing``), the solver's timings."""
    from retarget.checks.verify import check_reference, object_in_robot_depth
    from retarget.evaluation import evaluate_sequence
    from retarget.evaluation.sequence import json_safe
    from retarget.solver.problem import resample_demonstration

    result = evaluate_sequence(reference, demo)
    metrics = {**result.metrics, **grip_scores(result)}
    checks = check_reference(reference, resample_demonstration(demo, reference.fps)).as_dict()
    checks["object_in_robot_m"] = object_in_robot_depth(reference)
    # the robot's visual-mesh vertices into the object or the floor, and the object's surface into the robot
    checks["robot_penetration_m"] = max(checks["object_penetration_mesh_m"], checks["ground_penetration_mesh_m"])
    checks["penetration_m"] = max(checks["robot_penetration_m"], checks["object_in_robot_m"])
    timing = {"setup_s": None, "solve_s": None, "ms_per_frame": None, "frames": reference.num_frames,
              "retarget_s": None}
    if made is not None:  # retargeted by this run (a resumed variant's time was recorded in its first run)
        timing.update(setup_s=made.setup_s, solve_s=made.solve_s, ms_per_frame=made.ms_per_frame,
                      retarget_s=made.setup_s + made.solve_s)
    return json_safe({"metrics": metrics, "object_channels": result.details["object_channels"],
                      "object_pairs": result.details["object_pairs"], "checks": checks, "timing": timing})


def run_variant(job: VariantJob, cfg: RetargetConfig, substitution: SubstitutionConfig, min_recall: float,
                frame_bar: bool = False) -> tuple[str, str]:
    """Retarget (unless its reference exists), score and record one variant; returns (status,
    message) with status 'done', 'warning' (recall below ``min_recall``) or 'failed' (never raises)."""
    try:
        from otr_gym.reference import Reference
        from retarget.clip import retarget_timed

        start = time.perf_counter()
        demo, swapped = _variant_demo(job, substitution)
        made = None
        if job.output.is_file():
            reference = Reference.load(job.output)
        else:
            progress = None
            if frame_bar:
                from tqdm import tqdm

                frames = swapped.num_frames if cfg.fps is None else \
                    math.floor(swapped.duration_s * cfg.fps + 1e-9) + 1
                bar = tqdm(total=frames, desc=job.spec.name, unit="frame", leave=False)

                def progress(_t: int) -> None:
                    bar.update(1)
            # the native row is the plain retarget: the substitution machinery would also give back
            # the captured object, but with exact witnesses where the native solve uses the grid's
            reference, made = retarget_timed(demo if job.spec.is_native else swapped, cfg, progress)
            if frame_bar:
                bar.close()
            reference.metadata["substitution"] = {**swapped.source["substitution"],
                                                  "substitution_config": asdict(substitution)}
            reference.save(job.output)
        record = measure_variant(reference, demo, made)
        obj = swapped.source["substitution"]["object"]
        record.update({"variant": job.spec.name, "label": job.spec.label(obj), "shape": job.spec.shape,
                       "scale": list(job.spec.scale), "uniform_scale": job.spec.uniform, "object": obj,
                       "native": job.spec.is_native, "demonstration": str(job.demo), "reference": str(job.output),
                       "free": list(job.free)})
        record["timing"]["job_s"] = time.perf_counter() - start  # this run: retarget (if needed) and scoring
        grip = record["metrics"]["grip_recall"]
        warnings = []
        if grip is None or grip < min_recall:
            shown = "undefined" if grip is None else f"{100 * grip:.0f} %"
            warnings.append(f"the hands reach the {obj} in {shown} of the demonstrated grip (below "
                            f"{100 * min_recall:.0f} %): the substitute may be too big for the G1's reach")
        record["warnings"] = warnings
        write_json(job.record, record)
        summary = (f"{job.output} (object R {_pct(record['metrics']['object_recall'])}, grip R {_pct(grip)}, "
                   f"penetration {1e3 * record['checks']['penetration_m']:.2f} mm, "
                   + (f"retarget {record['timing']['retarget_s']:.0f} s)" if made is not None else "made earlier)"))
        if warnings:
            return "warning", f"{job.spec.name}: {warnings[0]}; {summary}"
        return "done", summary
    except Exception as exc:  # noqa: BLE001 - one variant's failure must not stop the batch
        detail = "" if isinstance(exc, (ValueError, FileNotFoundError, KeyError)) else "\n" + traceback.format_exc()
        return "failed", f"{job.spec.name} of {job.demo}: {type(exc).__name__}: {exc}{detail}"


def _pct(x) -> str:
    return "–" if x is None else f"{100 * x:.0f} %"


# ------------------------------------------------------------------ reports


def _get(record: dict, path: tuple[str, ...]):
    value = record
    for key in path:
        value = value.get(key) if isinstance(value, dict) else None
    return value


def _cell(value, factor: float, digits: int) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    return f"{value * factor:.{digits}f}"


def format_variants_table(records: list[dict]) -> str:
    """Markdown table in the layout of the paper's Table IV: one row per variant (the captured
    object at ×1 first, as the paper's native row), object dd, R, P, J, drift, then our checks."""
    columns = list(TABLE_COLUMNS)
    if any(_get(r, ("metrics", "pair_recall")) is not None for r in records):
        columns.insert(5, PAIR_COLUMN)
    header = ["Variant"] + [f"{h} {u}".strip() for _, h, u, _, _ in columns] + ["note"]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] + ["--:"] * len(columns) + ["---"]) + "|"]

    def paper_order(r: dict):  # the native row, the captured object resized, the library in Table IV's order, files
        native = r["shape"] == ORIGINAL and r["scale"] == [1.0, 1.0, 1.0]
        rank = SHAPE_NAMES.index(r["shape"]) if r["shape"] in SHAPE_NAMES else len(SHAPE_NAMES)
        return (not native, rank, r["shape"], r["scale"])

    for r in sorted(records, key=paper_order):
        label = r["label"] + (" (native)" if r["shape"] == ORIGINAL and r["scale"] == [1.0, 1.0, 1.0] else "")
        cells = [_cell(_get(r, path), f, d) for path, _, _, f, d in columns]
        note = "; ".join(r.get("warnings", [])) or ""
        lines.append("| " + " | ".join([label] + cells + [note]) + " |")
    return "\n".join(lines)


def plot_recall_precision(records: list[dict], path: str | Path, title: str = "") -> Path | None:
    """The paper's Fig. 5: recall and precision (%) against the uniform scale, per shape swept
    over two scales or more (every shape when none is): the grip (the hands against the
    object, the paper's figure) on the left, all body units against the object on the right;
    solid recall, dashed precision. None when no record has a uniform scale."""
    from retarget.evaluation.plots import _pyplot

    by_shape: dict[str, list[dict]] = {}
    for r in records:
        if r.get("uniform_scale") is not None:
            by_shape.setdefault(r["shape"], []).append(r)
    if not by_shape:
        return None
    swept = {k: v for k, v in by_shape.items() if len(v) > 1}
    by_shape = swept or by_shape
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(9.0, 3.4), sharey=True)
    for ax, prefix, what in zip(axes, ("grip", "object"), ("grip: hands", "object: all body units")):
        for k, (shape, rows) in enumerate(sorted(by_shape.items())):
            rows = sorted(rows, key=lambda r: r["uniform_scale"])
            x = [r["uniform_scale"] for r in rows]
            name = rows[0]["object"] if shape == ORIGINAL else Path(shape).stem
            for key, style, label in (("recall", "-o", "recall"), ("precision", "--s", "precision")):
                y = [100 * v if v is not None else float("nan") for v in (r["metrics"].get(f"{prefix}_{key}")
                                                                         for r in rows)]
                ax.plot(x, y, style, color=f"C{k % 10}", ms=4, label=f"{name} {label}")
        ax.set_title(what, fontsize=9)
        ax.set_xlabel("object scale (×)")
        ax.set_ylim(0, 102)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("recall / precision (%)")
    axes[0].legend(fontsize=7, loc="lower right")
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path, dpi=130)


def read_records(out: Path, demo: Path) -> list[dict]:
    """Every variant record of ``demo`` in ``out`` (also those of earlier runs with other shapes
    or scales: the folder is one dataset); unreadable records are skipped with a message."""
    records = []
    for path in sorted(Path(out).glob(f"{Path(demo).stem}__*.json")):
        try:
            record = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            print(f"warning: {path}: unreadable record ({exc}); run again with --overwrite to redo it", file=sys.stderr)
            continue
        if isinstance(record, dict) and "variant" in record and "metrics" in record:
            records.append(record)
    return records


# ------------------------------------------------------------------ command line


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("demo", type=Path, metavar="DEMO", help="the demonstration (OMOMO .pt, our .npz, …)")
    p.add_argument("--object", type=Path, default=None, metavar="MESH",
                   help="the demonstration's object mesh for OMOMO clips (default: looked up next to the clip)")
    p.add_argument("--shapes", default=ORIGINAL,
                   help="comma-separated substitutes: original (the captured object), ball, drum, capsule, rugby, "
                        "torus, cube, board, beam, or mesh files .obj/.stl/.ply (z up) (default: original)")
    p.add_argument("--scales", default="1",
                   help="size factors: START:STOP:STEP (inclusive), comma-separated values, per-axis SXxSYxSZ "
                        "(x: longer horizontal side, z: up) (default: 1)")
    p.add_argument("--out", type=Path, required=True, help="output folder (references, records, table, plot)")
    p.add_argument("--workers", type=int, default=1, help="parallel worker processes (default: 1)")
    p.add_argument("--object-name", default=None,
                   help="the object to substitute (default: the demonstration's only manipulated object)")
    p.add_argument("--free", action="append", default=[], metavar="NAME",
                   help="make this static object (e.g. table) a decision variable too (repeatable)")
    p.add_argument("--keep-mesh-frame", action="store_true",
                   help="mesh files are already in the captured object's frame (no re-orientation or centring)")
    p.add_argument("--min-recall", type=float, default=0.5,
                   help="warn when a variant's grip recall (hands on the object) is below this fraction "
                        "(default: 0.5)")
    p.add_argument("--fps", type=float, default=None, help="output and solve rate in Hz (default: 50)")
    p.add_argument("--config", type=Path, default=None, help="retarget YAML configuration (default: built-in)")
    p.add_argument("--overwrite", action="store_true", help="redo variants whose outputs already exist")


def _check_inputs(args: argparse.Namespace) -> tuple[RetargetConfig, list[VariantJob]]:
    """Everything that can be refused before any work: raises ValueError/ConfigError naming it."""
    from retarget.inputs.demonstration import InvalidDemonstrationError
    from retarget.inputs.meshes import InvalidMeshError
    from retarget.solver.substitute import free_objects, manipulated_object

    cfg = load_config(args.config, fps=args.fps)
    if cfg.mode != "native":
        raise ConfigError(f"variants need the native mode (the substitute is a decision variable), got '{cfg.mode}'")
    if args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    if not 0.0 <= args.min_recall <= 1.0:
        raise ConfigError(f"--min-recall must be a fraction in [0, 1], got {args.min_recall}")
    shapes = parse_shapes(args.shapes)
    scales = parse_scales(args.scales)
    for shape in shapes:
        if ShapeSpec(shape).is_file:
            load_shape_mesh(shape)  # InvalidMeshError naming the file
    try:
        demo = _demonstration(args.demo, args.object)
        if args.free:
            demo = free_objects(demo, tuple(args.free))
        manipulated_object(demo, args.object_name)
    except KeyError as exc:
        raise ConfigError(str(exc.args[0])) from exc
    except (InvalidDemonstrationError, InvalidMeshError, FileNotFoundError) as exc:
        raise ConfigError(str(exc)) from exc
    jobs = variant_jobs(args.demo, args.object, shapes, scales, args.out, args.object_name, tuple(args.free),
                        args.keep_mesh_frame)
    return cfg, jobs


def main(args: argparse.Namespace) -> int:
    from retarget.inputs.meshes import InvalidMeshError

    try:
        cfg, jobs = _check_inputs(args)
    except (ConfigError, UnknownShapeError, InvalidMeshError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    if args.overwrite:
        for job in jobs:
            job.record.unlink(missing_ok=True)
            job.output.unlink(missing_ok=True)
    todo = [j for j in jobs if not j.record.is_file()]
    skipped = len(jobs) - len(todo)
    if skipped:
        print(f"{skipped} of {len(jobs)} variants already done: skipped (use --overwrite to redo them)")
    run = functools.partial(run_variant, cfg=cfg, substitution=SubstitutionConfig(), min_recall=args.min_recall)
    results = run_batch(todo, run, args.workers, "variants", "variant")
    failures = [message for _, status, message in results if status == "failed"]
    warned = [message for _, status, message in results if status == "warning"]

    records = read_records(out, args.demo)
    if records:
        write_json(out / "variants.json", {"demonstration": str(args.demo), "variants": records,
                                           "failed": [m.splitlines()[0] for m in failures]})
        table = format_variants_table(records)
        with atomic_path(out / "variants.md") as tmp:
            tmp.write_text(f"# Variants of {args.demo.name}\n\n{table}\n", encoding="utf-8")
        print(table)
        plot = plot_recall_precision(records, out / "recall_precision_vs_scale.png", args.demo.stem)
        if plot is not None:
            print(f"wrote {out / 'variants.md'}, {out / 'variants.json'}, {plot}")
    print(f"variants: {len(todo) - len(failures)} done ({len(warned)} with a warning), skipped {skipped}, "
          f"failed {len(failures)} (of {len(jobs)})")
    for message in failures:
        print(f"FAILED {message}", file=sys.stderr)
    return 1 if failures else 0
