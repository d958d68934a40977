"""A reference's robot surface against its ground and itself, for references that have no
demonstration to score against (Holosoma's, or ``otr clear-ground``'s output).

    python benchmarks/surface_on_ground.py REF [REF ...] [--terrain MESH] [--true-surface] [--json F]

Per reference, over every frame: how deep the G1's visual meshes go below the ground (the floor
z = 0 and, with ``--terrain``, the clip's terrain along its faces' normals, ``retarget.checks.ground``),
the deepest link and the frames deeper than 1 mm and 1 cm; the same for the hands alone (the
wrist yaw links, which carry the rubber hands); and self-penetration (``retarget.evaluation
.self_collision``: p95 over frames, the paper's *self*, and the worst frame). Without
``--true-surface`` each link's depth is grown by its mesh error bound (an upper bound for
Unitree's surface, as ``benchmarks/fidelity.py``); with it, Unitree's original meshes (the mjlab
wheel, fetched once) are used themselves. Links are posed by our G1's kinematics from the
reference's configurations: a file's own body poses may come from another model (Holosoma's
``torso_link`` lies 1 cm off ours at the same configuration).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

HANDS = ("left_wrist_yaw_link", "right_wrist_yaw_link")
FRAME_CHUNK = 64  # frames posed at once (bounds the (frames, vertices, 3) temporaries)


def ground_depth(reference, ground, margins: dict[str, float]) -> dict[str, np.ndarray]:
    """Body -> (T,) m: how deep its visual mesh (grown by its margin) lies below ``ground`` (0: above)."""
    from otr_gym.robot_geometry import posed_vertices, visual_meshes

    meshes = visual_meshes()
    out = {}
    for body, mesh in meshes.items():
        i = reference.body_index([body])[0]
        depth = np.zeros(reference.num_frames)
        for start in range(0, reference.num_frames, FRAME_CHUNK):
            rows = slice(start, start + FRAME_CHUNK)
            verts = posed_vertices(mesh, reference.body_pos_w[rows, i], reference.body_quat_w[rows, i])
            height, _ = ground.under(verts)
            depth[rows] = np.maximum(margins.get(body, 0.0) - height.min(axis=1), 0.0)
        out[body] = depth
    return out


def measure(path: Path, ground, margins: dict[str, float]) -> dict:
    from otr_gym.reference import Reference
    from retarget.evaluation.self_collision import g1_self_model, self_penetration

    loaded = Reference.load(path)
    reference = Reference.from_qpos(loaded.qpos(), loaded.fps)  # posed by our G1, see the module doc
    depth = ground_depth(reference, ground, margins)
    bodies = list(depth)
    stacked = np.stack([depth[b] for b in bodies])  # (bodies, T)
    worst = stacked.max(axis=0)
    hands = np.stack([depth[b] for b in HANDS]).max(axis=0)
    model = g1_self_model()
    idx = reference.body_index(list(model.links))
    selfpen = self_penetration(list(model.meshes), reference.body_pos_w[:, idx], reference.body_quat_w[:, idx],
                               model.pairs)
    return {"reference": str(path), "frames": reference.num_frames,
            "ground_m": float(worst.max()), "ground_link": bodies[int(np.argmax(stacked.max(axis=1)))],
            "frames_over_1mm": int((worst > 1e-3).sum()), "frames_over_1cm": int((worst > 1e-2).sum()),
            "hands_m": float(hands.max()), "hand_frames_over_1cm": int((hands > 1e-2).sum()),
            "self_p95_m": selfpen.percentile_m(95), "self_max_m": float(selfpen.depth_m.max())}


def table(rows: list[dict], surface: str) -> str:
    lines = [f"surface: {surface}",
             "| reference | frames | into the ground: deepest mm (link) | frames > 1 mm / > 1 cm | hands: deepest mm, "
             "frames > 1 cm | self p95 / max mm |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {'/'.join(Path(r['reference']).parts[-2:])} | {r['frames']} | "
                     f"{1e3 * r['ground_m']:.1f} ({r['ground_link']}) "
                     f"| {r['frames_over_1mm']} / {r['frames_over_1cm']} | {1e3 * r['hands_m']:.1f}, "
                     f"{r['hand_frames_over_1cm']} | {1e3 * r['self_p95_m']:.2f} / {1e3 * r['self_max_m']:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("references", nargs="+", type=Path, help="reference .npz files")
    ap.add_argument("--terrain", help="terrain mesh the clips were recorded on (their world frame, metres)")
    ap.add_argument("--true-surface", action="store_true",
                    help="Unitree's original meshes (mjlab wheel) instead of the shipped ones plus their bound")
    ap.add_argument("--json", type=Path, help="write the rows here (atomically)")
    args = ap.parse_args(argv)
    if args.true_surface:
        from otr_gym.true_surface import use_original_meshes

        use_original_meshes()
    from otr_gym import robot
    from otr_gym.io import write_json
    from otr_gym.robot_geometry import surface_margin_m
    from retarget.checks.ground import Ground

    try:
        ground = Ground.from_mesh(args.terrain) if args.terrain else Ground.floor()
    except ValueError as exc:
        print(f"surface_on_ground: {exc}", file=sys.stderr)
        return 2
    margins = {} if args.true_surface else dict(zip(robot.BODY_NAMES, surface_margin_m()))
    rows = []
    for path in args.references:
        try:
            rows.append(measure(path, ground, margins))
        except ValueError as exc:  # a missing or unreadable reference: named
            print(f"surface_on_ground: {exc}", file=sys.stderr)
            return 2
    surface = ("Unitree's original meshes" if args.true_surface else "shipped meshes + their error bound") + \
        f"; ground: {ground.describe()}"
    print(table(rows, surface))
    if args.json:
        print(f"wrote {write_json(args.json, {'surface': surface, 'rows': rows})}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
