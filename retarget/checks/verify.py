"""Solver-independent checks of a retargeted reference: what a user must be able to trust.

``check_reference(reference, demo)`` measures, from the stored motion alone:

* penetration of the G1 **visual-mesh vertices** into the ground (min z) and into every object
  (exact signed distance to the object mesh, ``retarget.inputs.meshes.signed_distance``, whose sign
  survives the holes of scanned meshes), next to the solver's own per-link probe distances
  (the reference's contact annotations);
* joint position limits and joint velocity limits (finite differences of the stored joints);
* object contact hold: over the frames where a demonstrated hand is within ``contact_m`` of an
  object, the fraction where the robot's hand on that side is too (the robot measured against
  the reference's own object mesh: a substitute's, when the reference carries one);
* the lowest object vertex over time (an object must not sink into the floor).

The demonstration must be the one the reference was made from, at the reference's rate and in
its world (native mode; see ``retarget.solver.problem.resample_demonstration``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from otr_gym import robot
from otr_gym.robot_geometry import posed_vertices, visual_meshes
from otr_gym.rotations import quat_to_matrix
from retarget.geometry.dynamics import ObjectMass
from retarget.inputs.meshes import as_trimesh, object_mesh, signed_distance
from retarget.solver.substitute import SubstituteObject

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
        # the robot meets the reference's own mesh (a substitute, when it carries one); the
        # demonstrated hands met the captured object
        mesh = object_mesh(src.vertices, src.faces, f"object '{track.name}'")
        if track.mesh_vertices is not None and track.mesh_faces is not None:
            mesh = object_mesh(track.mesh_vertices, track.mesh_faces, f"{reference.source}: mesh of '{track.name}'")
        captured = object_mesh(src.vertices, src.faces, f"object '{track.name}'")
        if isinstance(src, SubstituteObject) and src.demonstrated_mesh is not None:
            captured = src.demonstrated_mesh
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
            near = np.all((local > captured.bounds[0] - contact_m) & (local < captured.bounds[1] + contact_m), axis=2)
            human_d = np.full(T, np.inf)
            t_idx, v_idx = np.nonzero(near)
            if len(t_idx):
                d, _, _ = signed_distance(captured, local[t_idx, v_idx])
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


def object_in_robot_depth(reference, spacing_m: float = 0.005, prefilter_m: float = 0.003) -> float:
    """Deepest point of a carried object's surface inside a G1 link's visual mesh (m, 0 if none).

    The other direction of ``object_penetration_mesh_m``: a box edge or corner can cut into a
    link between the link's vertices. The object surface (the reference's mesh) is sampled
    every ~``spacing_m`` plus its vertices. Points are screened with the links' 5 mm distance
    grids (``retarget.solver.problem.robot_link_grids``, error ≤ 0.3 mm), and those closer than
    ``prefilter_m`` are measured exactly (signed distance, winding-number sign).
    """
    from retarget.geometry.channels import sample_surface
    from retarget.solver.problem import robot_link_grids

    meshes = visual_meshes()
    names = [b for b in robot.BODY_NAMES if b in meshes]
    body = np.array(reference.body_index(names))
    grid_of = np.array([robot.BODY_NAMES.index(b) for b in names])
    grids = robot_link_grids(0.05)
    links = [as_trimesh(meshes[b].vertices, meshes[b].faces, f"G1 link {b}") for b in names]
    centre = np.stack([0.5 * (m.bounds[0] + m.bounds[1]) for m in links])
    radius = np.array([np.linalg.norm(m.vertices - c, axis=1).max() for m, c in zip(links, centre)])
    link_rot = quat_to_matrix(reference.body_quat_w[:, body])  # (T, L, 3, 3)
    link_pos = reference.body_pos_w[:, body]
    centre_w = np.einsum("tlij,lj->tli", link_rot, centre) + link_pos
    deepest = 0.0
    for track in reference.objects:
        if track.mesh_vertices is None or track.mesh_faces is None:
            continue
        mesh = object_mesh(track.mesh_vertices, track.mesh_faces, f"{reference.source}: mesh of '{track.name}'")
        pts = np.concatenate([mesh.vertices, sample_surface(mesh, 1.0 / spacing_m**2).points])
        o_centre = 0.5 * (mesh.bounds[0] + mesh.bounds[1])
        o_radius = float(np.linalg.norm(pts - o_centre, axis=1).max())
        rot = quat_to_matrix(track.quat_w)
        o_centre_w = rot @ o_centre + track.pos_w
        meet = np.linalg.norm(centre_w - o_centre_w[:, None], axis=-1) < radius + o_radius  # (T, L)
        for k in np.flatnonzero(meet.any(axis=0)):
            local = []
            for t in np.flatnonzero(meet[:, k]):
                x_l = (pts @ rot[t].T + track.pos_w[t] - link_pos[t, k]) @ link_rot[t, k]  # Rᵀ(x − p)
                x_l = x_l[np.linalg.norm(x_l - centre[k], axis=1) < radius[k]]
                d, _, inside = grids.distance(x_l, np.full(len(x_l), grid_of[k]))
                local.append(x_l[inside & (d < prefilter_m)])
            local = np.concatenate(local)
            if len(local):
                d, _, _ = signed_distance(links[k], local)
                deepest = max(deepest, float(-d.min()))
    return deepest


def configure_parser(p) -> None:
    """``otr verify``'s arguments."""
    p.add_argument("reference", help="retargeted reference .npz (native mode)")
    p.add_argument("--demo", help="the demonstration it was made from (for the kinematic checks)")
    p.add_argument("--object", default=None, help="object mesh when the demonstration file lacks it")
    p.add_argument("--terrain", help="terrain mesh the clip was recorded on (trimesh-readable, metres, the clip's "
                   "world frame; the file given to env.terrain.meshes): the feasibility check stands the robot on it "
                   "as well as on the floor z = 0")
    p.add_argument("--object-mass-kg", type=float, default=ObjectMass().default_kg, metavar="KG",
                   help="mass of a carried object (kg): its weight and acceleration load the hands holding it in the "
                        "torques and the base wrench (default %(default)s: the box environment's heaviest draw)")
    p.add_argument("--feasibility-png", help="write the dynamic-feasibility timeline (PNG) here")
    p.add_argument("--feasibility-json", help="write the dynamic-feasibility summary (JSON) here")


def main(args) -> int:
    """``otr verify REFERENCE [--demo DEMO] [--object MESH] [--terrain MESH] [--feasibility-png PNG]``:
    print the checks against the demonstration (with ``--demo``) and the dynamic feasibility
    (``retarget.checks.feasibility``). A missing or unreadable reference or terrain: a message naming
    the file, exit code 2."""
    import sys

    from retarget.checks.ground import load_clip_on_ground

    try:
        reference, ground = load_clip_on_ground(args.reference, args.terrain)
    except ValueError as exc:  # InvalidReferenceError, InvalidMeshError: the file named
        print(f"otr verify: {exc}", file=sys.stderr)
        return 2
    if args.demo is not None:
        _print_checks(reference, args)
    from retarget.checks.feasibility import FeasibilityCfg, write_feasibility
    if args.object_mass_kg < 0:
        print(f"otr verify: --object-mass-kg {args.object_mass_kg:g}: a mass cannot be negative", file=sys.stderr)
        return 2
    if args.object is not None:  # a reference without its object's mesh (Holosoma's) is judged with this one
        _attach_mesh(reference, args.object)
    cfg = FeasibilityCfg(object_mass=ObjectMass(args.object_mass_kg))
    write_feasibility(reference, args.feasibility_png, args.feasibility_json, cfg=cfg, ground=ground)
    return 0


def _attach_mesh(reference, path: str) -> None:
    """Give the reference's objects that carry no mesh the mesh in ``path`` (object frame, m)."""
    from retarget.inputs.meshes import load_mesh

    meshless = [obj for obj in reference.objects if obj.mesh_vertices is None]
    if meshless:
        mesh = load_mesh(path)
        for obj in meshless:
            obj.mesh_vertices, obj.mesh_faces = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)


def _print_checks(reference, args) -> None:
    from retarget.inputs.readers import load_demonstration
    from retarget.solver.problem import resample_demonstration

    demo = resample_demonstration(load_demonstration(args.demo, args.object), reference.fps)
    limit_mm = 0.3
    checks = {**check_reference(reference, demo).as_dict(), "object_in_robot_m": object_in_robot_depth(reference)}
    for key, value in checks.items():
        note = ""
        if key.endswith(("penetration_mesh_m", "in_robot_m")):
            note = "ok" if value <= limit_mm * 1e-3 else f"beyond {limit_mm} mm"
        print(f"{key:28s} {value:.6g} {note}")

