"""``otr inspect FILE…``: what is in a demonstration, reference or deploy-log file.

References (Holosoma / BeyondMimic / mjlab / ours .npz) report frames, fps, duration, bodies,
objects, velocity consistency and contact statistics from their annotations; anything else is
read as a demonstration (AMASS, OMOMO .pt, BVH, our demonstration .npz) and reports its parts,
objects, stature and ground/object contact statistics of the posed human surface. Deploy logs
(``otr deploy --log``) report cycle timing, missed deadlines, stage changes and tracking error.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from otr_gym.reference import InvalidReferenceError, Reference

CONTACT_EPS_M = 0.02  # the paper's ε_eval


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("files", nargs="+", type=Path, help="demonstration or reference files")
    p.add_argument("--object", type=Path, help="object mesh for demonstrations that need one (OMOMO)")
    from retarget.bvh import add_arguments

    add_arguments(p)


def is_reference_file(path: Path) -> bool:
    if path.suffix != ".npz":
        return False
    try:
        with np.load(path, allow_pickle=False) as npz:
            return "joint_pos" in npz.files and "body_pos_w" in npz.files
    except (OSError, ValueError):
        return False


def _is_deploy_log(path: Path) -> bool:
    if path.suffix != ".npz":
        return False
    try:
        with np.load(path, allow_pickle=False) as npz:
            return "meta" in npz.files and "wake_ns" in npz.files
    except (OSError, ValueError):
        return False


def reference_summary(ref: Reference) -> list[tuple[str, str]]:
    rows = [
        ("kind", "reference"),
        ("frames", f"{ref.num_frames} @ {ref.fps:g} fps ({ref.duration_s:.2f} s)"),
        ("bodies", f"{len(ref.body_names)}: {', '.join(ref.body_names[:4])}, …"),
        ("root height", f"{ref.root_pos_w[:, 2].min():.3f} – {ref.root_pos_w[:, 2].max():.3f} m"),
        ("root path", f"{np.linalg.norm(np.diff(ref.root_pos_w[:, :2], axis=0), axis=1).sum():.2f} m"),
    ]
    for o in ref.objects:
        rows.append((f"object {o.name}", f"z {o.pos_w[:, 2].min():.3f} – {o.pos_w[:, 2].max():.3f} m, "
                     f"moves {np.linalg.norm(o.pos_w[-1] - o.pos_w[0]):.2f} m"
                     + (", mesh embedded" if o.mesh_vertices is not None else "")))
    vc = ref.velocity_consistency()
    rows.append(("velocity vs poses", ", ".join(f"{k} {v:.2g}" for k, v in vc.items())))
    if ref.contacts is not None:
        c = ref.contacts
        touching = c.in_contact(CONTACT_EPS_M)
        for j, channel in enumerate(c.channel_names):
            frac = touching[:, :, j].mean(axis=0)
            top = np.argsort(frac)[::-1][:4]
            rows.append((f"contact {channel}", ", ".join(f"{c.body_names[i]} {frac[i]:.0%}" for i in top if frac[i] > 0)
                         or "none"))
    if ref.metadata:
        rows.append(("metadata", ", ".join(f"{k}={v}" for k, v in sorted(ref.metadata.items())
                                           if not isinstance(v, (dict, list)))))
    return rows


def demonstration_summary(path: Path, object_mesh: Path | None, bvh=None) -> list[tuple[str, str]]:
    from retarget.demos import load_demonstration
    from retarget.meshes import as_trimesh, signed_distance
    from otr_gym.rotations import quat_apply_inverse

    demo = load_demonstration(path, object_mesh=object_mesh, bvh=bvh)
    rows = [
        ("kind", f"demonstration ({demo.source.get('format', '?')})"),
        ("frames", f"{demo.num_frames} @ {demo.fps:g} fps ({demo.duration_s:.2f} s)"),
        ("human", f"{len(demo.part_names)} parts, stature {demo.stature_m:.2f} m"),
    ]
    verts = demo.human_vertices_w()  # (T, V, 3) world
    part_of_vertex = demo.surface.vertex_part  # (V,)
    lowest = verts[..., 2].min(axis=1)
    rows.append(("lowest point", f"{lowest.min() * 1e3:.1f} – {lowest.max() * 1e3:.1f} mm above ground"))
    on_ground = [demo.part_names[k] for k in range(len(demo.part_names))
                 if (verts[:, part_of_vertex == k, 2].min(axis=1) < CONTACT_EPS_M).mean() > 0.05]
    rows.append(("ground contact", ", ".join(on_ground) or "none"))
    for o in demo.objects:
        mesh = as_trimesh(o.vertices, o.faces, o.name)
        stride = max(1, demo.num_frames // 60)
        frames = range(0, demo.num_frames, stride)
        near = np.zeros(len(demo.part_names))
        for t in frames:
            local = quat_apply_inverse(o.quat_w[t], verts[t] - o.pos_w[t])
            d, _, _ = signed_distance(mesh, local)
            for k in range(len(demo.part_names)):
                near[k] += d[part_of_vertex == k].min() < CONTACT_EPS_M
        parts = [f"{demo.part_names[k]} {near[k] / len(frames):.0%}" for k in np.argsort(near)[::-1][:4] if near[k]]
        rows.append((f"object {o.name}", f"{'static' if o.static else 'moves'}, {len(o.faces)} faces, "
                     f"z {o.pos_w[:, 2].min():.2f} – {o.pos_w[:, 2].max():.2f} m; contact: {', '.join(parts) or 'none'}"))
    return rows


def main(args: argparse.Namespace) -> int:
    status = 0
    for path in args.files:
        try:
            if is_reference_file(path):
                rows = reference_summary(Reference.load(path))
            elif _is_deploy_log(path):
                from agents.deploy.log import DeployLog, summary_rows

                rows = summary_rows(DeployLog.load(path))
            else:
                from retarget.bvh import options_from_args

                rows = demonstration_summary(path, args.object, options_from_args(args))
        except (InvalidReferenceError, ValueError, FileNotFoundError) as exc:
            print(f"{path}: error: {exc}")
            status = 1
            continue
        print(path)
        width = max(len(k) for k, _ in rows)
        for key, value in rows:
            print(f"  {key:<{width}}  {value}")
    return status
