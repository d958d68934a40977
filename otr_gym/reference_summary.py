"""What is in a reference file, as rows of (key, value) for a terminal: frames, bodies, root
path, objects, velocity consistency, contact statistics and metadata (``otr inspect``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from otr_gym.io import NpzError, npz_keys
from otr_gym.reference import Reference

#: Contact distance (m) under which a body counts as touching a channel: the paper's ε_eval.
CONTACT_EPS_M = 0.02


def has_reference_keys(keys) -> bool:
    """Whether an .npz file's array names are those of a reference (any supported layout)."""
    return "joint_pos" in keys and "body_pos_w" in keys


def is_reference_file(path: Path) -> bool:
    if path.suffix != ".npz":
        return False
    try:
        return has_reference_keys(npz_keys(path))
    except (NpzError, OSError):
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
