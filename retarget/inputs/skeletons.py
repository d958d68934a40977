"""From a BVH skeleton to the 22 SMPL-X parts (``retarget.inputs.human``).

* **Families** are recognised by joint names (``FAMILIES``; a ``name:`` namespace such as
  ``mixamorig:`` is ignored, case too); ``--skeleton-map`` YAML (``SMPL-X part: joint name``,
  ``joint/end`` for a joint's End Site) maps any other skeleton.
* **Missing parts**: parts a skeleton lacks (a third spine joint, a neck, collars) sit on the
  segment of the nearest mapped ancestor, at the SMPL-X mean body's proportion, and turn with it
  (``mapped_skeleton``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from retarget.inputs.bvh_file import BvhError, BvhFile, world_transforms

#: Per family, SMPL-X part -> candidate joint names (normalised: lower case, no namespace); the
#: first present wins; "?" marks a part the family may lack; "name/end" is that joint's End Site.
FAMILIES: dict[str, dict[str, tuple[str, ...]]] = {
    "Bandai Namco": {
        "Pelvis": ("hips",), "L_Hip": ("upperleg_l",), "R_Hip": ("upperleg_r",), "Spine1": ("spine",),
        "L_Knee": ("lowerleg_l",), "R_Knee": ("lowerleg_r",), "Spine2": ("?",), "L_Ankle": ("foot_l",),
        "R_Ankle": ("foot_r",), "Spine3": ("chest",), "L_Foot": ("toes_l",), "R_Foot": ("toes_r",),
        "Neck": ("neck",), "L_Collar": ("shoulder_l",), "R_Collar": ("shoulder_r",), "Head": ("head",),
        "L_Shoulder": ("upperarm_l",), "R_Shoulder": ("upperarm_r",), "L_Elbow": ("lowerarm_l",),
        "R_Elbow": ("lowerarm_r",), "L_Wrist": ("hand_l",), "R_Wrist": ("hand_r",),
    },
    "CMU / Motionbuilder": {
        "Pelvis": ("hips",), "L_Hip": ("leftupleg",), "R_Hip": ("rightupleg",), "Spine1": ("lowerback",),
        "L_Knee": ("leftleg",), "R_Knee": ("rightleg",), "Spine2": ("spine",), "L_Ankle": ("leftfoot",),
        "R_Ankle": ("rightfoot",), "Spine3": ("spine1",), "L_Foot": ("lefttoebase", "leftfoot/end"),
        "R_Foot": ("righttoebase", "rightfoot/end"), "Neck": ("neck1", "neck"), "L_Collar": ("leftshoulder", "?"),
        "R_Collar": ("rightshoulder", "?"), "Head": ("head",), "L_Shoulder": ("leftarm",),
        "R_Shoulder": ("rightarm",), "L_Elbow": ("leftforearm",), "R_Elbow": ("rightforearm",),
        "L_Wrist": ("lefthand",), "R_Wrist": ("righthand",),
    },
    "LAFAN1 / Ubisoft": {
        "Pelvis": ("hips",), "L_Hip": ("leftupleg",), "R_Hip": ("rightupleg",), "Spine1": ("spine",),
        "L_Knee": ("leftleg",), "R_Knee": ("rightleg",), "Spine2": ("spine1",), "L_Ankle": ("leftfoot",),
        "R_Ankle": ("rightfoot",), "Spine3": ("spine2",), "L_Foot": ("lefttoe",), "R_Foot": ("righttoe",),
        "Neck": ("neck",), "L_Collar": ("leftshoulder",), "R_Collar": ("rightshoulder",), "Head": ("head",),
        "L_Shoulder": ("leftarm",), "R_Shoulder": ("rightarm",), "L_Elbow": ("leftforearm",),
        "R_Elbow": ("rightforearm",), "L_Wrist": ("lefthand",), "R_Wrist": ("righthand",),
    },
    "Mixamo": {
        "Pelvis": ("hips",), "L_Hip": ("leftupleg",), "R_Hip": ("rightupleg",), "Spine1": ("spine",),
        "L_Knee": ("leftleg",), "R_Knee": ("rightleg",), "Spine2": ("spine1",), "L_Ankle": ("leftfoot",),
        "R_Ankle": ("rightfoot",), "Spine3": ("spine2",), "L_Foot": ("lefttoebase", "leftfoot/end"),
        "R_Foot": ("righttoebase", "rightfoot/end"), "Neck": ("neck",), "L_Collar": ("leftshoulder",),
        "R_Collar": ("rightshoulder",), "Head": ("head",), "L_Shoulder": ("leftarm",), "R_Shoulder": ("rightarm",),
        "L_Elbow": ("leftforearm",), "R_Elbow": ("rightforearm",), "L_Wrist": ("lefthand",),
        "R_Wrist": ("righthand",),
    },
    "Poser / CMU-Daz": {
        "Pelvis": ("hip",), "L_Hip": ("lthigh",), "R_Hip": ("rthigh",), "Spine1": ("abdomen",),
        "L_Knee": ("lshin",), "R_Knee": ("rshin",), "Spine2": ("abdomen2", "?"), "L_Ankle": ("lfoot",),
        "R_Ankle": ("rfoot",), "Spine3": ("chest",), "L_Foot": ("ltoe", "lfoot/end"),
        "R_Foot": ("rtoe", "rfoot/end"), "Neck": ("neck",), "L_Collar": ("lcollar",), "R_Collar": ("rcollar",),
        "Head": ("head",), "L_Shoulder": ("lshldr",), "R_Shoulder": ("rshldr",), "L_Elbow": ("lforearm",),
        "R_Elbow": ("rforearm",), "L_Wrist": ("lhand",), "R_Wrist": ("rhand",),
    },
}
#: Parts every skeleton must map (the rest may be missing: see the module docstring).
REQUIRED_PARTS = ("Pelvis", "L_Hip", "R_Hip", "L_Knee", "R_Knee", "L_Ankle", "R_Ankle", "L_Foot", "R_Foot", "Head",
                  "L_Shoulder", "R_Shoulder", "L_Elbow", "R_Elbow", "L_Wrist", "R_Wrist")


@dataclass(frozen=True)
class JointRef:
    """A point of the skeleton: a joint, or the End Site of a joint (``end=True``)."""

    joint: int
    end: bool = False


def normalise_name(name: str) -> str:
    """Lower case, without a ``namespace:`` prefix (Mixamo's ``mixamorig:``)."""
    return name.rsplit(":", 1)[-1].strip().lower()


def _resolve(bvh: BvhFile, spec: str) -> JointRef | None:
    lookup = {normalise_name(n): i for i, n in enumerate(bvh.joint_names)}
    name, _, suffix = spec.partition("/")
    index = lookup.get(normalise_name(name))
    if index is None:
        return None
    if suffix:
        return JointRef(index, True) if index in bvh.end_sites else None
    return JointRef(index)


def match_family(bvh: BvhFile) -> tuple[str, dict[str, JointRef]]:
    """The family whose required parts all resolve, with the most parts mapped; BvhError if none."""
    best, best_map, report = None, {}, []
    for family, table in FAMILIES.items():
        mapping, missing = {}, []
        for part, candidates in table.items():
            ref = next((r for r in (_resolve(bvh, c) for c in candidates if c != "?") if r is not None), None)
            if ref is not None:
                mapping[part] = ref
            elif "?" not in candidates:
                missing.append(part)
        report.append(f"{family}: {len(mapping)} parts, missing {missing}" if missing else f"{family}: ok")
        if not missing and (best is None or len(mapping) > len(best_map)):
            best, best_map = family, mapping
    if best is None:
        raise BvhError(f"{bvh.path}: skeleton not recognised (joints: {', '.join(bvh.joint_names[:40])}"
                       f"{' …' if len(bvh.joint_names) > 40 else ''}); families tried: {'; '.join(report)}. "
                       "Give --skeleton-map YAML mapping SMPL-X parts to joint names (retarget/inputs/skeletons.py)")
    return best, best_map


def load_skeleton_map(path: str | Path, bvh: BvhFile) -> dict[str, JointRef]:
    """A YAML mapping ``SMPL-X part: joint name`` (or ``joint/end``); problems name both files."""
    from retarget.inputs.human import PART_NAMES

    path = Path(path)
    if not path.is_file():
        raise BvhError(f"{path}: skeleton map not found")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise BvhError(f"{path}: not valid YAML ({exc})") from exc
    if not isinstance(data, dict):
        raise BvhError(f"{path}: must map SMPL-X part names to joint names, got {type(data).__name__}")
    unknown = sorted(str(k) for k in data if k not in PART_NAMES)
    if unknown:
        raise BvhError(f"{path}: unknown SMPL-X part(s) {unknown} (parts: {', '.join(PART_NAMES)})")
    mapping = {}
    for part, joint in data.items():
        ref = _resolve(bvh, str(joint))
        if ref is None:
            raise BvhError(f"{path}: joint {joint!r} (for part {part}) is not in {bvh.path} "
                           f"(joints: {', '.join(bvh.joint_names)})")
        mapping[part] = ref
    missing = [p for p in REQUIRED_PARTS if p not in mapping]
    if missing:
        raise BvhError(f"{path}: parts {missing} must be mapped (optional: spine, neck and collar parts)")
    return mapping


@dataclass
class MappedSkeleton:
    """The BVH joints mapped to the 22 parts, in our z-up metric world."""

    joint_of_part: list[int]  # BVH joint whose rotation each part follows
    pos_w: np.ndarray  # (T, 22, 3) joint positions
    rot_w: np.ndarray  # (T, 22, 3, 3) world rotations of those BVH joints (z-up world)
    tips: dict[str, np.ndarray]  # part -> (T, 3) position of a tip beyond it (hand, toe, head), if any
    missing: list[str]


def _tip(bvh: BvhFile, joint: int, pos: np.ndarray, rot: np.ndarray, offset_to_world: np.ndarray) -> np.ndarray | None:
    """Where a segment ends beyond ``joint`` (T, 3): the mean of its children, else its End Site
    (file offset times ``offset_to_world``, axes change and scale); None when both are (near) zero
    length. ``pos``/``rot`` are the joints' world poses in our axes (rot = C R Cᵀ)."""
    children = [c for c, p in enumerate(bvh.parents) if p == joint]
    if children:
        tip = pos[:, children].mean(axis=1)
        # a zero-length child (Xia's LeftFingerBase) passes on to its own children
        if np.linalg.norm(tip - pos[:, joint], axis=-1).mean() < 1e-3:
            tips = [t for t in (_tip(bvh, c, pos, rot, offset_to_world) for c in children) if t is not None]
            return np.mean(tips, axis=0) if tips else None
        return tip
    end = offset_to_world @ bvh.end_sites[joint] if joint in bvh.end_sites else np.zeros(3)
    if np.linalg.norm(end) > 1e-3:
        return pos[:, joint] + np.einsum("tab,b->ta", rot[:, joint], end)
    return None


def mapped_skeleton(bvh: BvhFile, mapping: dict[str, JointRef], to_world: np.ndarray, scale: float) -> MappedSkeleton:
    """The joints of ``mapping`` as the 22 parts in our z-up metric world (``to_world``: file axes
    -> ours (3, 3); ``scale``: metres per file unit), with the parts the skeleton lacks placed on
    their mapped ancestor's segment (module docstring) and the tips beyond hands, toes and head."""
    from retarget.inputs.human import PART_NAMES, PART_PARENTS, shape_basis

    pos, rot = world_transforms(bvh)
    pos = np.einsum("ab,tjb->tja", to_world, pos) * scale
    rot = to_world @ rot @ to_world.T
    rest = shape_basis().rest_joints
    frames = len(pos)
    part_pos = np.zeros((frames, len(PART_NAMES), 3))
    joint_of_part = [-1] * len(PART_NAMES)
    missing = []
    for k, part in enumerate(PART_NAMES):
        ref = mapping.get(part)
        if ref is None:
            missing.append(part)
            continue
        if ref.end:
            part_pos[:, k] = pos[:, ref.joint] + np.einsum("tab,b->ta", rot[:, ref.joint],
                                                           to_world @ bvh.end_sites[ref.joint] * scale)
        else:
            part_pos[:, k] = pos[:, ref.joint]
        joint_of_part[k] = ref.joint
    # missing parts sit on their mapped ancestor's segment towards the first mapped descendant
    for part in missing:
        k = PART_NAMES.index(part)
        ancestor = PART_PARENTS[k]
        while joint_of_part[ancestor] < 0:
            ancestor = PART_PARENTS[ancestor]
        child = next(c for c in range(len(PART_NAMES)) if PART_PARENTS[c] == k)
        while joint_of_part[child] < 0:
            child = next(c for c in range(len(PART_NAMES)) if PART_PARENTS[c] == child)
        a, b = np.linalg.norm(rest[k] - rest[ancestor]), np.linalg.norm(rest[child] - rest[k])
        part_pos[:, k] = part_pos[:, ancestor] + a / (a + b) * (part_pos[:, child] - part_pos[:, ancestor])
        joint_of_part[k] = joint_of_part[ancestor]
    tips = {}
    for part in ("L_Wrist", "R_Wrist", "L_Foot", "R_Foot", "Head"):
        ref = mapping[part]
        if not ref.end:
            tip = _tip(bvh, ref.joint, pos, rot, to_world * scale)
            if tip is not None:
                tips[part] = tip
    return MappedSkeleton(joint_of_part, part_pos, rot[:, joint_of_part], tips, missing)
