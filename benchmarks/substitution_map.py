"""Accuracy and cost of the object↔object witness map (retarget.solver.substitute.SurfaceMap).

Where the right answer is known: an identical substitute (every point must map onto itself)
and the captured object resized ×s about its centre (a point must map to s times its offset
from the centre). Prints, per case and setting, the error of mapped surface points (median,
p95, max, mm) and the time to build the two maps (four Sinkhorn plans, no cache):

    python benchmarks/substitution_map.py [--mesh ../shared/data/objects/largebox.obj]

Without the mesh file the synthetic box of ``retarget.inputs.synthetic`` (0.35 × 0.40 × 0.30 m) is used.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

from retarget.geometry.channels import sample_surface
from retarget.inputs.meshes import as_trimesh, load_mesh
from retarget.solver.substitute import SubstitutionConfig, surface_maps

DEFAULT_MESH = Path(__file__).resolve().parents[2] / "shared" / "data" / "objects" / "largebox.obj"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--mesh", type=Path, default=DEFAULT_MESH, help="captured object mesh (default: OMOMO large box)")
    p.add_argument("--scales", default="1,0.7,1.6", help="comma-separated uniform factors")
    args = p.parse_args()
    if args.mesh.is_file():
        mesh = load_mesh(args.mesh)
    else:
        box = trimesh.creation.box(extents=(0.35, 0.40, 0.30))
        mesh = as_trimesh(box.vertices, box.faces, "synthetic box")
    centre = mesh.bounds.mean(axis=0)
    points = sample_surface(mesh, 20000.0, seed=7).points  # off the plan's samples
    print(f"{mesh.name}: {len(points)} test points\n")
    print(f"{'scale':>5} {'samples':>7} {'debias':>6} | {'median':>6} {'p95':>6} {'max':>6} mm | {'build':>6} s")
    for scale in (float(s) for s in args.scales.split(",")):
        sub = as_trimesh((mesh.vertices - centre) * scale + centre, mesh.faces, f"×{scale}")
        truth = (points - centre) * scale + centre
        for samples in (1000, 2000):
            for debias in (False, True):
                with tempfile.TemporaryDirectory() as cache:
                    t = time.perf_counter()
                    to_sub, _ = surface_maps(mesh, sub, SubstitutionConfig(samples=samples, debias=debias),
                                             Path(cache))
                    build = time.perf_counter() - t
                err = 1e3 * np.linalg.norm(to_sub(points) - truth, axis=1)
                print(f"{scale:5.2f} {samples:7d} {debias!s:>6} | {np.median(err):6.2f} {np.quantile(err, 0.95):6.2f} "
                      f"{err.max():6.2f}    | {build:6.1f}")


if __name__ == "__main__":
    main()
