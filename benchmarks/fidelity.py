"""Retarget fidelity on the five shared clips: one table of what users measure.

    python benchmarks/fidelity.py [--data ../shared/data] [--out out/fidelity] [--references DIR]
                                  [--json fidelity.json] [--true-surface] [--config YAML]

Retargets (native scale, objects free) OMOMO ``sub3_largebox_003``, ``sub2_largetable_004``,
``sub2_woodchair_000`` and AMASS ``smplh_walk_jog_turn``, ``smplx_steps_deep_squat`` with the
current code (or scores the references already in ``--references``, e.g. made by an older
version), then scores each with the evaluation protocol (``retarget.evaluation``) and prints:
ground and object P/R/J, dd, dw, skate, clear, penetration into the ground and into the
objects, self-penetration p95, drift, the reference's dynamic feasibility (``otr verify``'s
measures: the share of frames over any limit, the peak limb jump, the peak torque over the
effort limit) and ms/frame.

Penetration is the deepest G1 visual-mesh vertex below the floor / inside an object over the
clip, plus the link's mesh error bound (``otr_gym.true_surface``): an upper bound for Unitree's
original surface. ``--true-surface`` scores with the original meshes themselves (downloaded
once from the mjlab wheel) instead of the shipped ones. ms/frame is this run's solve time per
output frame (setup excluded; with ``--references``, what the files recorded, if anything; the
machine's load is not controlled here, use ``benchmarks/retarget_speed.py`` for speed figures).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CLIPS = ("omomo/sub3_largebox_003.pt", "omomo/sub2_largetable_004.pt", "omomo/sub2_woodchair_000.pt",
         "amass/smplh_walk_jog_turn.npz", "amass/smplx_steps_deep_squat.npz")

#: (header, key, factor, digits) of the printed table.
COLUMNS = (
    ("gP", "ground_precision", 100, 0), ("gR", "ground_recall", 100, 0), ("gJ", "ground_jaccard", 100, 0),
    ("g dd", "ground_dd_m", 1e3, 1), ("skate", "skate_m_s", 100, 1), ("clear", "clear_m", 1e3, 1),
    ("oP", "object_precision", 100, 0), ("oR", "object_recall", 100, 0), ("oJ", "object_jaccard", 100, 0),
    ("o dd", "object_dd_m", 1e3, 1), ("o dw", "object_dw_m", 1e3, 0),
    ("pen g", "ground_penetration_m", 1e3, 2), ("pen o", "object_penetration_m", 1e3, 2),
    ("self95", "self_m", 1e3, 2), ("drift", "drift_m", 100, 1),
    ("flag", "flagged_share", 100, 1), ("limb", "limb_jump_peak_m", 100, 1), ("τ/eff", "torque_peak_ratio", 1, 2),
    ("ms/f", "ms_per_frame", 1, 1),
)
UNITS = ("%", "%", "%", "mm", "cm/s", "mm", "%", "%", "%", "mm", "mm", "mm", "mm", "mm", "cm", "%", "cm", "×", "")


def penetration(result, margin_per_unit: np.ndarray) -> tuple[float, float]:
    """(ground, objects) deepest penetration (m) of any robot unit over the clip, each unit's
    depth grown by its links' mesh error bound (0 when nothing penetrates even then)."""
    depth = -(result.d_m - margin_per_unit[None, :, None])  # (T, U, C): > 0 inside (conservative)
    ground = max(0.0, float(depth[..., 0].max()))
    objects = max(0.0, float(depth[..., 1:].max())) if depth.shape[2] > 1 else float("nan")
    return ground, objects


def unit_margins(units) -> np.ndarray:
    from otr_gym import robot
    from otr_gym.robot_geometry import surface_margin_m

    margin = dict(zip(robot.BODY_NAMES, surface_margin_m()))
    return np.array([max(margin[lk] for lk in u.links) for u in units])


def score(ref_path: Path, demo_path: Path, true_surface: bool, ms_per_frame: float | None) -> dict[str, float]:
    from otr_gym.reference import Reference
    from retarget.checks.feasibility import check_feasibility
    from retarget.evaluation.sequence import evaluate_sequence
    from retarget.evaluation.units import default_units
    from retarget.inputs.readers import load_demonstration

    ref = Reference.load(ref_path)
    demo = load_demonstration(demo_path)
    units = default_units()
    res = evaluate_sequence(ref, demo, units=units)
    margins = np.zeros(len(units)) if true_surface else unit_margins(units)
    ground, objects = penetration(res, margins)
    if ms_per_frame is None:  # references made elsewhere: the solve time they recorded, if any
        solver = ref.metadata.get("solver", {}) if isinstance(ref.metadata, dict) else {}
        ms_per_frame = float(solver.get("ms_per_frame", float("nan")))
    feasibility = check_feasibility(ref).brief()
    return {**res.metrics, "ground_penetration_m": ground, "object_penetration_m": objects,
            "flagged_share": feasibility["flagged_share"], "limb_jump_peak_m": feasibility["limb_jump_peak_m"],
            "torque_peak_ratio": feasibility["torque_peak_ratio"],
            "feasibility_frames_over": feasibility["frames_over"], "ms_per_frame": ms_per_frame}


def format_table(rows: dict[str, dict[str, float]]) -> str:
    head = f"{'clip':24s}" + "".join(f"{h:>7s}" for h, *_ in COLUMNS)
    unit = f"{'':24s}" + "".join(f"{u:>7s}" for u in UNITS)
    lines = [head, unit, "-" * len(head)]
    for name, m in rows.items():
        cells = []
        for _, key, factor, digits in COLUMNS:
            v = m.get(key, float("nan"))
            cells.append(f"{'—':>7s}" if v is None or not np.isfinite(v) else f"{v * factor:7.{digits}f}")
        lines.append(f"{name:24s}" + "".join(cells))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data", help="the shared data folder")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "fidelity", help="where new references are written")
    ap.add_argument("--references", type=Path, default=None,
                    help="score the references in this folder (named after the clips) instead of retargeting")
    ap.add_argument("--clips", nargs="*", default=list(CLIPS), help="clips relative to --data")
    ap.add_argument("--json", type=Path, default=None, help="write every metric here")
    ap.add_argument("--config", type=Path, default=None,
                    help="retarget with this YAML (as `otr retarget --config`; default configs/retarget/default.yaml)")
    ap.add_argument("--true-surface", action="store_true",
                    help="score against Unitree's original meshes (mjlab wheel) instead of the shipped ones")
    args = ap.parse_args(argv)
    if args.true_surface and args.references is None:
        ap.error("--true-surface scores existing references: give --references DIR")
    if args.true_surface:
        from otr_gym.true_surface import use_original_meshes

        use_original_meshes()

    rows = {}
    for clip in args.clips:
        demo_path = args.data / clip
        name = Path(clip).stem
        ms_per_frame = None
        if args.references is not None:
            ref_path = args.references / f"{name}.npz"
        else:
            from retarget.clip import retarget_timed
            from retarget.config import load_config
            from retarget.inputs.readers import load_demonstration

            ref_path = args.out / f"{name}.npz"
            start = time.perf_counter()
            reference, timing = retarget_timed(load_demonstration(demo_path), load_config(args.config))
            reference.save(ref_path)
            ms_per_frame = timing.ms_per_frame
            print(f"{name}: retargeted in {time.perf_counter() - start:.1f} s", flush=True)
        rows[name] = score(ref_path, demo_path, args.true_surface, ms_per_frame)
        print(f"{name}: scored", flush=True)
    print(format_table(rows))
    if args.json is not None:
        from otr_gym.io import write_json
        from retarget.evaluation.sequence import json_safe

        write_json(args.json, json_safe(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
