"""Solver-independent checks of a retargeted reference: what a user must be able to trust.

``check_reference(reference, demo)`` measures, from the stored motion alone:

* penetration of the G1 **visual-mesh vertices** into the ground (min z) and into every object
  (exact signed distance to the object mesh, ``retarget.meshes.signed_distance``, whose sign
  survives the holes of scanned meshes), next to the solver's own per-link probe distances
  (the reference's contact annotations);
* joint position limits and joint velocity limits (finite differences of the stored joints);
* object contact hold: over the frames where a demonstrated hand is within ``contact_m`` of an
  object, the fraction where the robot's hand on that side is too;
* the lowest object vertex over time (an object must not sink into the floor).

The demonstration must be the one the reference was made from, at the reference's rate and in
its world (native mode; see ``retarget.problem.resample_demonstration``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from otr_gym import robot
from otr_gym.robot_geometry import posed_vertices, visual_meshes
from otr_gym.rotations import quat_to_matrix
from retarget.meshes import object_mesh, signed_distance

#: Demonstrated and robot hands compared by the contact-hold check (human part, G1 link).
HANDS = (("L_Wrist", "left_wrist_yaw_link"), ("R_Wrist", "right_wrist_yaw_link"))


@dataclass(frozen=True)
class ReferenceChecks:
    """Measured figures (SI units; fractions in [0, 1])."""

    ground_penetration_mesh_m: float  # deepest visual-mesh vertex below z = 0 (0 if none)
    object_penetration_mesh_m: float  # deepest visual-mesh vertex inside any object (0 if none)
    probe_min_distance_m: float  # smallest per-link probe distance of the annotations
    joint_limit_excess_rad: float  # largest excursion beyond a joint limit (0 if none)
    joint_speed_ratio: float  # largest |q̇| / velocity limit
    hand_hold: float  # fraction of demonstrated hand-contact frames with the robot hand in contact
    hand_contact_frames: int  # number of demonstrated (frame, hand) contacts
    object_min_height_m: float  # lowest object vertex over the clip (inf without objects)
    frames: int

    def as_dict(self) -> dict:
        return asdict(self)


def _robot_vertices(reference) -> tuple[list[str], list[np.ndarray]]:
    meshes = visual_meshes()
    names = [b for b in robot.BODY_NAMES if b in meshes]
    idx = reference.body_index(names)
    return names, [posed_vertices(meshes[b], reference.body_pos_w[:, i], reference.body_quat_w[:, i])
                   for b, i in zip(names, idx)]


def check_reference(reference, demo, contact_m: float = 0.02) -> ReferenceChecks:
    """Measure the reference against its demonstration (see the module doc)."""
    T = reference.num_frames
    if demo.num_frames != T:
        raise ValueError(f"{reference.source}: {T} frames but the demonstration '{demo.name}' has "
                         f"{demo.num_frames}; resample it to {reference.fps} Hz first")
    names, verts = _robot_vertices(reference)
    ground = -min(0.0, min(float(v[..., 2].min()) for v in verts))

    objects = {o.name: o for o in demo.objects}
    object_pen = 0.0
    hold_hits, hold_total = 0, 0
    min_height = np.inf
    for track in reference.objects:
        src = objects.get(track.name)
        if src is None:
            continue
        mesh = object_mesh(src.vertices, src.faces, f"object '{track.name}'")
        rot = quat_to_matrix(track.quat_w)  # (T, 3, 3) object → world
        lo, hi = mesh.bounds
        obj_w = np.einsum("tij,vj->tvi", rot, mesh.vertices) + track.pos_w[:, None]
        min_height = min(min_height, float(obj_w[..., 2].min()))
        link_dist = {}
        for name, v in zip(names, verts):
            local = np.einsum("tji,tvj->tvi", rot, v - track.pos_w[:, None])  # Rᵀ(x − τ)
            near = np.all((local > lo - contact_m) & (local < hi + contact_m), axis=2)
            dist = np.full(T, np.inf)
            t_idx, v_idx = np.nonzero(near)
            if len(t_idx):
                d, _, _ = signed_distance(mesh, local[t_idx, v_idx])
                object_pen = max(object_pen, float(-d.min()))
                np.minimum.at(dist, t_idx, d)
            link_dist[name] = dist
        human_w = demo.surface.posed_vertices(demo.part_pos_w, demo.part_quat_w)
        part_of = np.asarray(demo.surface.vertex_part)
        demo_rot = quat_to_matrix(src.quat_w)
        for part, link in HANDS:
            k = demo.surface.part_names.index(part)
            hv = human_w[:, part_of == k]
            local = np.einsum("tji,tvj->tvi", demo_rot, hv - src.pos_w[:, None])
            near = np.all((local > lo - contact_m) & (local < hi + contact_m), axis=2)
            human_d = np.full(T, np.inf)
            t_idx, v_idx = np.nonzero(near)
            if len(t_idx):
                d, _, _ = signed_distance(mesh, local[t_idx, v_idx])
                np.minimum.at(human_d, t_idx, d)
            in_contact = np.maximum(human_d, 0.0) < contact_m
            hold_total += int(in_contact.sum())
            hold_hits += int((in_contact & (np.maximum(link_dist[link], 0.0) < contact_m)).sum())

    joints = reference.dof_pos
    excess = max(float(np.max(robot.JOINT_LOWER - joints)), float(np.max(joints - robot.JOINT_UPPER)), 0.0)
    speed = np.abs(np.diff(joints, axis=0)) * reference.fps / robot.VELOCITY_LIMIT
    probe_min = float(reference.contacts.distance.min()) if reference.contacts is not None else np.nan
    return ReferenceChecks(
        ground_penetration_mesh_m=ground, object_penetration_mesh_m=object_pen, probe_min_distance_m=probe_min,
        joint_limit_excess_rad=excess, joint_speed_ratio=float(speed.max()) if len(speed) else 0.0,
        hand_hold=hold_hits / hold_total if hold_total else float("nan"), hand_contact_frames=hold_total,
        object_min_height_m=min_height, frames=T)


def main(argv: list[str] | None = None) -> int:
    """``python -m retarget.verify REFERENCE [--demo DEMO] [--object MESH] [--feasibility-png PNG]``: print
    the checks against the demonstration (with ``--demo``) and the dynamic feasibility
    (``retarget.feasibility``)."""
    import argparse

    from otr_gym.reference import Reference

    p = argparse.ArgumentParser(prog="python -m retarget.verify", description=__doc__.split("\n\n")[0])
    p.add_argument("reference", help="retargeted reference .npz (native mode)")
    p.add_argument("--demo", help="the demonstration it was made from (for the kinematic checks)")
    p.add_argument("--object", default=None, help="object mesh when the demonstration file lacks it")
    p.add_argument("--feasibility-png", help="write the dynamic-feasibility timeline (PNG) here")
    p.add_argument("--feasibility-json", help="write the dynamic-feasibility summary (JSON) here")
    args = p.parse_args(argv)
    reference = Reference.load(args.reference)
    if args.demo is not None:
        _print_checks(reference, args)
    from retarget.feasibility import write_feasibility

    write_feasibility(reference, args.feasibility_png, args.feasibility_json)
    return 0


def _print_checks(reference, args) -> None:
    from retarget.demos import load_demonstration
    from retarget.problem import resample_demonstration

    demo = resample_demonstration(load_demonstration(args.demo, args.object), reference.fps)
    limit_mm = 0.3
    for key, value in check_reference(reference, demo).as_dict().items():
        note = ""
        if key.endswith("penetration_mesh_m"):
            note = "ok" if value <= limit_mm * 1e-3 else f"beyond {limit_mm} mm"
        print(f"{key:28s} {value:.6g} {note}")


if __name__ == "__main__":
    raise SystemExit(main())
