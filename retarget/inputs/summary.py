"""What is in a demonstration file, as rows of (key, value) for a terminal: frames, parts,
stature, the lowest point, the parts on the ground and near each object (``otr inspect``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from otr_gym.reference_summary import CONTACT_EPS_M


def demonstration_summary(path: Path, object_mesh: Path | None, bvh=None) -> list[tuple[str, str]]:
    from otr_gym.rotations import quat_apply_inverse
    from retarget.inputs.meshes import as_trimesh, signed_distance
    from retarget.inputs.readers import load_demonstration

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
                     f"z {o.pos_w[:, 2].min():.2f} – {o.pos_w[:, 2].max():.2f} m; "
                     f"contact: {', '.join(parts) or 'none'}"))
    return rows
