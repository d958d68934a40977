"""The elastic re-solve of failed QPs against one slack per row, on real QPs.

    python benchmarks/elastic_qp.py [--scale 6] [--max-full-rows 2000]

Retargets the test suite's too-big substitute (the synthetic box carry's frames 166–172, its box
``--scale`` times as wide, a 2 cm grid, as ``otr variants`` does), records every QP that ProxQP
failed and the elastic re-solve took (``retarget.solver.qp_workspace``), then solves each again with a
slack on every row (the re-solve before the working set, n + m variables; skipped above
``--max-full-rows`` rows) and prints one row per QP: rows, working-set time, QPs solved and the
largest set, all-rows time, and the largest difference between the two steps. Since the
re-solve is an interior-point method over x (``elastic_ipm``), its QPs and largest set read 0
unless it fell back to the working set.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=6.0, help="width factor of the substituted box")
    ap.add_argument("--max-full-rows", type=int, default=2000, help="skip the all-rows solve above this many rows")
    args = ap.parse_args(argv)

    from retarget.cli.variants import VariantJob, run_variant
    from retarget.config import RetargetConfig
    from retarget.geometry.channels import GeometryConfig
    from retarget.inputs.shapes import ShapeSpec
    from retarget.inputs.synthetic import generate
    from retarget.solver.qp_workspace import QPWorkspace
    from retarget.solver.substitute import SubstitutionConfig

    recorded: list[tuple[list[np.ndarray], np.ndarray, float, list[int], float]] = []
    elastic, with_slacks = QPWorkspace._solve_elastic, QPWorkspace._solve_with_slacks
    sets: list[int] = []  # rows of each working-set QP of the re-solve under way

    def counted(self, H, g, C, *rest):
        sets.append(C.shape[0])
        return with_slacks(self, H, g, C, *rest)

    def timed(self, *qp):
        sets.clear()
        start = time.perf_counter()
        x = elastic(self, *qp)
        recorded.append(([np.array(a, copy=True) for a in qp], x, time.perf_counter() - start, list(sets),
                         self.eps_abs))
        return x

    demo = generate("box_carry", seed=0, fps=30.0)
    s = slice(166, 172)
    demo = replace(demo, name="grasp", part_pos_w=demo.part_pos_w[s], part_quat_w=demo.part_quat_w[s],
                   objects=[replace(o, pos_w=o.pos_w[s], quat_w=o.quat_w[s]) for o in demo.objects],
                   annotations={k: v[s] for k, v in demo.annotations.items()})
    QPWorkspace._solve_elastic, QPWorkspace._solve_with_slacks = timed, counted
    try:
        with tempfile.TemporaryDirectory() as tmp:
            source = demo.save(Path(tmp) / "grasp.npz")
            job = VariantJob(source, None, ShapeSpec("original", (1.0, args.scale, 1.0)), Path(tmp) / "wide.npz")
            start = time.perf_counter()
            status, message = run_variant(job, RetargetConfig(geometry=GeometryConfig(grid_resolution_m=0.02)),
                                          SubstitutionConfig(samples=500), min_recall=0.5)
            print(f"retarget ({status}): {time.perf_counter() - start:.1f} s; {message}")
    finally:
        QPWorkspace._solve_elastic, QPWorkspace._solve_with_slacks = elastic, with_slacks

    print(f"{'rows':>6} {'re-solve s':>14} {'QPs':>4} {'largest set':>12} {'all rows s':>11} {'max |dx|':>10}")
    for qp, x, seconds, set_rows, eps_abs in recorded:
        m = qp[2].shape[0]
        if m > args.max_full_rows:
            full_s, dx = "skipped", "–"
        else:
            start = time.perf_counter()
            full = QPWorkspace(eps_abs)._solve_with_slacks(*qp)
            full_s, dx = f"{time.perf_counter() - start:.2f}", f"{np.abs(full - x).max():.1e}"
        print(f"{m:>6} {seconds:>14.2f} {len(set_rows):>4} {max(set_rows, default=0):>12} {full_s:>11} {dx:>10}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
