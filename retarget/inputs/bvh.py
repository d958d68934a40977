"""BVH motion capture -> Demonstration (mannequin-x body shaped to the skeleton).

The steps, each in its own module:

* **Parsing** and forward kinematics of the file's skeleton: ``retarget.inputs.bvh_file``
  (our own small parser; every error names the file, the line and the joint).
* **Skeleton families** and ``--skeleton-map``: ``retarget.inputs.skeletons`` maps the joints to
  the 22 SMPL-X parts (``retarget.inputs.human``), placing parts a skeleton lacks.
* **Units** come from the body's size (here): the stature implied by the skeleton's bone lengths
  (pose-independent) in each candidate unit, the one closest to 1.70 m wins (m, dm, cm, mm,
  inch, foot, CMU's ASF unit of 1/0.45 inch); none between 1.0 and 2.4 m: scaled to 1.70 m.
* **Up axis** (here) is the axis along which the head is above the ankles over the clip (the rest
  pose of Maya-style rigs such as Bandai Namco's and LAFAN1's is not upright). A y-up file
  facing +z ends facing +x in our z-up world (x, y, z -> z, x, y).
* **Alignment** of each BVH joint frame with its SMPL-X part frame, a constant rotation found
  from the motion whatever the rest pose (flat, rigid feet): ``retarget.inputs.bvh_alignment``.
* **Body** (here): ``fit_shape`` fits the mannequin-x shape coefficients and the pelvis track to the
  joints (least squares, as for OMOMO); the mean and largest joint errors go to ``source``.
  Parts are then posed by the fitted body's forward kinematics with the legs bent onto the
  rig's ankle track (``follow_ankles``), and the feet are put on the
  floor as for every reader (``retarget.inputs.readers`` grounding), after levelling a tilted capture
  floor (``level_floor``).

What was assumed (family, units, up axis, stature, fit error) is printed once per file
(stderr) and kept in ``Demonstration.source["bvh"]``.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from otr_gym.rotations import matrix_to_quat, quat_normalize, quat_to_matrix
from retarget.inputs.bvh_alignment import part_alignments, unit_vectors
from retarget.inputs.bvh_file import BvhError, parse_bvh, world_transforms
from retarget.inputs.demonstration import Demonstration
from retarget.inputs.skeletons import load_skeleton_map, mapped_skeleton, match_family

UNITS_M: dict[str, float] = {
    "metres": 1.0, "decimetres": 0.1, "centimetres": 0.01, "millimetres": 0.001, "inches": 0.0254,
    "feet": 0.3048, "CMU ASF units (1/0.45 inch)": 0.0254 / 0.45,
}
UNIT_ALIASES = {"m": "metres", "dm": "decimetres", "cm": "centimetres", "mm": "millimetres", "in": "inches",
                "inch": "inches", "ft": "feet", "cmu": "CMU ASF units (1/0.45 inch)"}
TYPICAL_STATURE_M = 1.70
STATURE_RANGE_M = (1.0, 2.4)
UP_AXES = ("x", "y", "z", "-x", "-y", "-z")


# ------------------------------------------------------------------ units and up axis


def _chain_stature(points: dict[str, np.ndarray], rest_joints: np.ndarray) -> float:
    """Stature implied by bone lengths (pose-independent): ankle -> knee -> hip -> pelvis -> head
    lengths of both legs (mean) and the trunk, times the SMPL-X mean body's stature / same lengths."""
    from retarget.inputs.human import HumanModel, part_index

    def length(p: dict, names) -> float:
        return sum(float(np.linalg.norm(p[a] - p[b])) for a, b in zip(names[:-1], names[1:], strict=True))

    legs = [("L_Ankle", "L_Knee", "L_Hip", "Pelvis"), ("R_Ankle", "R_Knee", "R_Hip", "Pelvis")]
    trunk = ("Pelvis", "Head")
    smplx = {n: rest_joints[part_index([n])[0]] for n in ("L_Ankle", "L_Knee", "L_Hip", "R_Ankle", "R_Knee", "R_Hip",
                                                           "Pelvis", "Head")}
    ours = sum(length(points, leg) for leg in legs) / 2 + length(points, trunk)
    theirs = sum(length(smplx, leg) for leg in legs) / 2 + length(smplx, trunk)
    return ours * HumanModel().stature_m / theirs


def detect_units(stature_file_units: float) -> tuple[str, float]:
    """(unit name, metres per file unit): the candidate that makes the stature closest to 1.70 m."""
    name = min(UNITS_M, key=lambda u: abs(math.log(stature_file_units * UNITS_M[u] / TYPICAL_STATURE_M)))
    stature = stature_file_units * UNITS_M[name]
    if STATURE_RANGE_M[0] <= stature <= STATURE_RANGE_M[1]:
        return name, UNITS_M[name]
    return f"unknown (scaled to a {TYPICAL_STATURE_M:.2f} m stature)", TYPICAL_STATURE_M / stature_file_units


def axes_to_z_up(up: str) -> np.ndarray:
    """Rotation (3, 3) taking file axes to our z-up world: ``up`` -> +z, the next axis cyclically
    (y-up: z, the usual facing) -> +x."""
    if up not in UP_AXES:
        raise ValueError(f"up axis must be one of {UP_AXES}, got {up!r}")
    i = "xyz".index(up[-1])
    u = np.eye(3)[i] * (-1.0 if up.startswith("-") else 1.0)
    f = np.eye(3)[(i + 1) % 3]
    return np.stack([f, np.cross(u, f), u])


def detect_up(head: np.ndarray, ankles: np.ndarray) -> tuple[str, float]:
    """Signed axis along which the head is above the ankles over the clip, and how clearly
    (fraction of the mean head-ankle vector on that axis)."""
    v = (head - ankles).mean(axis=0)
    i = int(np.argmax(np.abs(v)))
    return ("-" if v[i] < 0 else "") + "xyz"[i], float(abs(v[i]) / (np.linalg.norm(v) + 1e-12))


# ------------------------------------------------------------------ options


@dataclass(frozen=True)
class BvhOptions:
    """How to read BVH files: None means detect. ``units`` is a name of UNITS_M, an alias
    (m, cm, mm, in, ft, cmu) or metres per file unit; ``up`` one of UP_AXES."""

    skeleton_map: str | None = None
    units: str | None = None
    up: str | None = None
    quiet: bool = False


def _units_override(text: str) -> tuple[str, float]:
    key = UNIT_ALIASES.get(text.lower(), text)
    if key in UNITS_M:
        return key, UNITS_M[key]
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"--units must be one of {sorted(UNIT_ALIASES)} or metres per file unit, got {text!r}") \
            from None
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"--units must be > 0, got {text!r}")
    return f"{value:g} m per unit", value


# ------------------------------------------------------------------ the body


#: Ridge of the shape fit (``fit_shape``; m² per unit coefficient²). BVH joints are placed by each
#: rig's own conventions, not SMPL-X's, so an exact fit drives coefficients to ±7 (a distorted
#: figure) to chase those placements; 1e-5 keeps them within ±4 for about 1 cm more mean
#: joint error on the three shared walks (1e-6: 2.0–3.5 cm, |β| ≤ 7.5; 1e-5: 2.8–4.3 cm, |β| ≤ 3.8).
SHAPE_RIDGE_M2 = 1e-5

#: Floors tilted less than this are left alone; a clip must travel at least MIN_FLOOR_SPAN_M
#: for its footprints to define a plane.
MIN_FLOOR_TILT_DEG = 0.2
MIN_FLOOR_SPAN_M = 1.0


def level_floor(surface, part_pos: np.ndarray, part_quat: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Turn the clip so that its floor is horizontal: captures whose floor (or calibration) is
    not level put the feet deeper into z = 0 the further the subject walks (ganimator's CMU walk
    rises 8 cm over 3.5 m). The floor is the plane through the footprints: the per-frame lowest
    surface points, keeping the lower half of the residuals three times (the swing frames lie
    above it). Returns the turned poses and the tilt (deg; 0 when left alone)."""
    from otr_gym.rotations import quat_from_rotvec, quat_mul

    verts = surface.posed_vertices(part_pos, part_quat)  # (T, V, 3)
    lowest = verts[np.arange(len(verts)), verts[..., 2].argmin(axis=1)]  # (T, 3)
    # footprints lie along the path: only the slope along its main direction is observable
    xy = lowest[:, :2] - lowest[:, :2].mean(axis=0)
    direction = np.linalg.svd(xy, full_matrices=False)[2][0]
    along = xy @ direction
    if np.ptp(along) < MIN_FLOOR_SPAN_M:
        return part_pos, part_quat, 0.0
    keep = np.ones(len(lowest), dtype=bool)
    for _ in range(3):
        slope, _ = np.polyfit(along[keep], lowest[keep, 2], 1)
        residual = lowest[:, 2] - slope * along
        keep = residual <= np.median(residual[keep])
    span = float(np.ptp(along[keep]))
    tilt = float(np.degrees(np.arctan(abs(slope))))
    if tilt < MIN_FLOOR_TILT_DEG or span < MIN_FLOOR_SPAN_M:
        return part_pos, part_quat, 0.0
    normal = unit_vectors(np.array([-slope * direction[0], -slope * direction[1], 1.0]))
    axis = np.cross(normal, [0.0, 0.0, 1.0])
    turn = quat_from_rotvec(unit_vectors(axis) * np.radians(tilt))
    centre = lowest[keep].mean(axis=0)
    rot = quat_to_matrix(turn)
    return (centre + (part_pos - centre) @ rot.T, quat_normalize(quat_mul(turn, part_quat)), tilt)


def follow_ankles(part_pos: np.ndarray, part_quat: np.ndarray, joints_w: np.ndarray) -> np.ndarray:
    """Part positions with each leg bent onto the skeleton's ankle track.

    The fitted body's forward kinematics puts its ankles where its own bone lengths and the
    rig's segment directions lead, and the gap to the rig's ankles changes as the legs swing:
    a planted rig foot slides under the body (2 cm of length mismatch at 3 rad/s is 6 cm/s).
    The gap, less its median in the foot's frame (the rigs' ankle joints sit elsewhere in the
    foot than SMPL-X's, which is no motion), moves the ankle and toes fully and the knee in
    proportion to its place along the leg; the hips stay. The thigh and shin pieces then miss
    their joints by that much (a few millimetres to centimetres).
    """
    from retarget.inputs.human import PART_NAMES

    out = part_pos.copy()
    rot = quat_to_matrix(part_quat)
    for side in "LR":
        hip, knee, ankle, toe = (PART_NAMES.index(f"{side}_{j}") for j in ("Hip", "Knee", "Ankle", "Foot"))
        gap = joints_w[:, ankle] - part_pos[:, ankle]
        local = np.einsum("tba,tb->ta", rot[:, ankle], gap)
        gap = gap - np.einsum("tab,b->ta", rot[:, ankle], np.median(local, axis=0))
        thigh = np.linalg.norm(part_pos[:, knee] - part_pos[:, hip], axis=-1)
        shin = np.linalg.norm(part_pos[:, ankle] - part_pos[:, knee], axis=-1)
        out[:, knee] += (thigh / (thigh + shin))[:, None] * gap
        out[:, ankle] += gap
        out[:, toe] += gap
    return out


# ------------------------------------------------------------------ the reader


def read_bvh(path: str | Path, options: BvhOptions | None = None, ground: bool = True) -> Demonstration:
    """A BVH file as a Demonstration (module docstring); BvhError names the file and problem."""
    from retarget.inputs.demonstration import ground_shift
    from retarget.inputs.human import PART_NAMES, PART_PARENTS, HumanModel, fit_shape, shape_basis

    options = options or BvhOptions()
    path = Path(path)
    bvh = parse_bvh(path)
    if options.skeleton_map:
        family, mapping = f"map {options.skeleton_map}", load_skeleton_map(options.skeleton_map, bvh)
    else:
        family, mapping = match_family(bvh)
    if bvh.num_frames < 2:
        raise BvhError(f"{path}: needs at least 2 frames, has {bvh.num_frames}")

    # units from bone lengths of the rest pose (pose-independent)
    rest_pos, _ = world_transforms(bvh, rest=True)
    rest_points = {part: rest_pos[0, ref.joint] for part, ref in mapping.items() if not ref.end}
    stature_units = _chain_stature(rest_points, shape_basis().rest_joints)
    try:
        unit_name, scale = _units_override(options.units) if options.units else detect_units(stature_units)
    except ValueError as exc:
        raise BvhError(f"{path}: {exc}") from exc
    unit_how = "given" if options.units else f"detected from the skeleton's size ({stature_units:.3g} units tall)"

    # up axis from the motion: where the head is relative to the ankles
    pos_file, _ = world_transforms(bvh)
    head = pos_file[:, mapping["Head"].joint]
    ankles = 0.5 * (pos_file[:, mapping["L_Ankle"].joint] + pos_file[:, mapping["R_Ankle"].joint])
    if options.up:
        if options.up not in UP_AXES:
            raise BvhError(f"{path}: --up must be one of {UP_AXES}, got {options.up!r}")
        up, up_how = options.up, "given"
    else:
        up, clarity = detect_up(head, ankles)
        up_how = f"detected: head above the ankles along it ({clarity:.0%} of their mean offset)"
        if clarity < 0.7:
            raise BvhError(f"{path}: cannot tell the up axis (the head is above the ankles along {up} for only "
                           f"{clarity:.0%} of their offset); give --up")
    to_world = axes_to_z_up(up)

    sk = mapped_skeleton(bvh, mapping, to_world, scale)
    align, how = part_alignments(sk)
    part_quat = quat_normalize(matrix_to_quat(sk.rot_w @ align))
    for side in "LR":  # rigid feet (module docstring)
        part_quat[:, PART_NAMES.index(f"{side}_Foot")] = part_quat[:, PART_NAMES.index(f"{side}_Ankle")]
    fit = fit_shape(sk.pos_w, part_quat, ridge_m2=SHAPE_RIDGE_M2)
    model = HumanModel(fit.shape)
    part_pos = follow_ankles(model.forward_kinematics(part_quat, fit.pelvis_pos_w), part_quat, sk.pos_w)
    tilt_deg = 0.0
    if ground:
        part_pos, part_quat, tilt_deg = level_floor(model.surface, part_pos, part_quat)
    shift = ground_shift(model.surface, part_pos, part_quat) if ground else 0.0
    part_pos[..., 2] += shift

    info = {
        "family": family, "units": unit_name, "metres_per_unit": scale, "units_how": unit_how, "up_axis": up,
        "up_how": up_how, "missing_parts": sk.missing, "roll_from": how,
        "joint_of_part": {p: bvh.joint_names[j] for p, j in zip(PART_NAMES, sk.joint_of_part, strict=True)},
        "stature_m": model.stature_m, "joint_fit_mean_m": float(fit.joint_error_m.mean()),
        "joint_fit_max_m": float(fit.joint_error_m.max()), "ground_shift_m": shift, "floor_tilt_deg": tilt_deg,
    }
    info["statement"] = (
        f"{path.name}: skeleton {family} ({22 - len(sk.missing)} of 22 parts mapped"
        f"{', placed: ' + ', '.join(sk.missing) if sk.missing else ''}); units {unit_name} ({unit_how}); "
        f"up axis {up} ({up_how}); mannequin-x body fitted to the joints: stature {model.stature_m:.2f} m, "
        f"joint error mean {100 * info['joint_fit_mean_m']:.1f} cm, max {100 * info['joint_fit_max_m']:.1f} cm; "
        f"feet put on the floor (shift {100 * shift:+.1f} cm"
        f"{f', floor levelled by {tilt_deg:.2f}°' if tilt_deg else ''})")
    if not options.quiet:
        print(info["statement"], file=sys.stderr)
    return Demonstration(
        name=path.stem, fps=bvh.fps, part_names=PART_NAMES, part_parents=PART_PARENTS, part_pos_w=part_pos,
        part_quat_w=part_quat, surface=model.surface, shape=model.shape, stature_m=model.stature_m,
        source={"format": "bvh", "path": str(path), "ground_shift_m": shift,
                "joint_fit_mean_m": info["joint_fit_mean_m"], "joint_fit_max_m": info["joint_fit_max_m"],
                "bvh": info})



# ------------------------------------------------------------------ command-line options


def add_arguments(p) -> None:
    """``--skeleton-map``, ``--units``, ``--up`` for commands that read demonstrations."""
    p.add_argument("--skeleton-map", type=str, default=None, metavar="YAML",
                   help="BVH: map of SMPL-X part -> joint name, for skeletons of no known family")
    p.add_argument("--units", type=str, default=None, metavar="UNIT",
                   help="BVH: length unit (m, cm, mm, in, ft, cmu, or metres per unit; default: from the body's size)")
    p.add_argument("--up", choices=UP_AXES, default=None, help="BVH: up axis of the file (default: detected)")


def options_from_args(args) -> BvhOptions:
    return BvhOptions(skeleton_map=getattr(args, "skeleton_map", None), units=getattr(args, "units", None),
                      up=getattr(args, "up", None))
