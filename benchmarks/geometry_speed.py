"""Speed of the proximity geometry and OT correspondences (retarget.geometry.channels / retarget.solver.transport).

Prints a table: grid build and cache load per mesh, query and geodesic time per 1 000 probes,
OT time for the largest human-part/G1-link pair. Run on one core for comparable numbers:

    taskset -c 0 python benchmarks/geometry_speed.py [--largebox PATH]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

from retarget.geometry.channels import SDFChannel
from retarget.inputs.meshes import as_trimesh, load_mesh

DEFAULT_LARGEBOX = Path(__file__).resolve().parents[2] / "shared" / "data" / "objects" / "largebox.obj"


def best_ms(fn, repeats: int = 30) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times))


def channel_rows(name: str, mesh, cache: Path) -> list[tuple[str, str]]:
    t = time.perf_counter()
    ch = SDFChannel.from_mesh(mesh, cache_dir=cache)
    build = time.perf_counter() - t
    t = time.perf_counter()
    SDFChannel.from_mesh(mesh, cache_dir=cache)
    load = time.perf_counter() - t
    rng = np.random.default_rng(0)
    lo, hi = mesh.bounds
    rows = [(f"{name}: grid {'x'.join(map(str, ch.grid.shape))} + geodesics ({len(ch.geodesics.points)}) build",
             f"{build:.2f} s"), (f"{name}: cache load", f"{1e3 * load:.0f} ms")]
    # probes within 5 cm of the surface (the solver's typical in-band probes), and uniform in the band
    x_band = rng.uniform(lo - 0.15, hi + 0.15, size=(20000, 3))
    near = x_band[np.abs(ch.query(x_band).d) < 0.05][:5000]
    for label, x in (("near surface", near), ("uniform in band", x_band[:5000])):
        n = len(x)
        fast = best_ms(lambda x=x: ch.query(x))
        exact = best_ms(lambda x=x: ch.query(x, exact_witness=True), 5)
        rows.append((f"{name}: query, {label} ({n} probes)", f"{fast / n * 1e3:.3f} ms/1000"))
        rows.append((f"{name}: query exact_witness, {label}", f"{exact / n * 1e3:.3f} ms/1000"))
    w = ch.query(near).w
    w_hat = w[rng.permutation(len(w))]
    rows.append((f"{name}: geodesic ({len(w)} pairs)",
                 f"{best_ms(lambda: ch.geodesic(w, w_hat)) / len(w) * 1e3:.3f} ms/1000"))
    return rows


def ot_rows(cache: Path) -> list[tuple[str, str]]:
    from otr_gym import robot
    from otr_gym.robot_geometry import visual_meshes
    from otr_gym.rotations import quat_to_matrix
    from retarget.geometry.channels import sample_surface
    from retarget.inputs.human import G1_LINK_PARTS, PART_NAMES, HumanModel, g1_tpose_body_poses, human_tpose
    from retarget.solver.transport import ot_assignment

    human = HumanModel()
    pos, quat = human_tpose(human)
    rot = quat_to_matrix(quat)
    parts = [PART_NAMES.index(p) for p in G1_LINK_PARTS["torso_link"]]
    src = np.concatenate([sample_surface(as_trimesh(human.surface.vertices[k], human.surface.faces[k],
                                                    PART_NAMES[k]), 2000.0, k).points @ rot[k].T + pos[k]
                          for k in parts])
    k = robot.BODY_NAMES.index("torso_link")
    m = visual_meshes()["torso_link"]
    link_pos, link_quat = g1_tpose_body_poses()
    tgt = sample_surface(as_trimesh(m.vertices, m.faces, "torso_link"), 2000.0, k).points @ \
        quat_to_matrix(link_quat[k]).T + link_pos[k]
    t = time.perf_counter()
    ot_assignment(src, tgt)
    return [(f"OT torso_link ({len(src)} x {len(tgt)} points)", f"{time.perf_counter() - t:.2f} s")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--largebox", type=Path, default=DEFAULT_LARGEBOX, help="scanned OMOMO box mesh (.obj)")
    args = parser.parse_args()
    b = trimesh.creation.box(extents=[0.4, 0.3, 0.2])
    meshes = [("box 0.4x0.3x0.2", as_trimesh(b.vertices, b.faces, "box"))]
    if args.largebox.is_file():
        meshes.append(("largebox scan", load_mesh(args.largebox)))
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        for name, mesh in meshes:
            rows += channel_rows(name, mesh, Path(cache))
        rows += ot_rows(Path(cache))
    width = max(len(r[0]) for r in rows)
    print(f"{'what':<{width}}  time")
    for what, value in rows:
        print(f"{what:<{width}}  {value}")


if __name__ == "__main__":
    main()
