"""BVH motion capture -> Demonstration (mannequin-x body shaped to the skeleton).

Why our own parser: ``bvhio`` (the maintained PyPI reader) loops forever on a truncated MOTION
block (its line reader never sees the end of the file), pins exact versions of its two
dependencies and names neither file nor joint in its errors. This one is small, reads the
MOTION block with one NumPy conversion, and every error names the file, the line and the joint.

Semantics (the common reading of the format, as Blender's and MotionBuilder's importers do):
a joint's local transform is a translation — its OFFSET, replaced axis by axis by its position
channels when it has any (Bandai Namco files give every joint six channels) — followed by the
rotation channels composed in the listed order (``Zrotation Xrotation Yrotation`` is
Rz·Rx·Ry acting on column vectors), angles in degrees.

From a skeleton to the 22 SMPL-X parts (``retarget.inputs.human``):

* **Families** are recognised by joint names (``FAMILIES``; a ``name:`` namespace such as
  ``mixamorig:`` is ignored, case too); ``--skeleton-map`` YAML (``SMPL-X part: joint name``,
  ``joint/end`` for a joint's End Site) maps any other skeleton. Parts a skeleton lacks (a
  third spine joint, a neck, collars) sit on the segment of the nearest mapped ancestor, at
  the SMPL-X mean body's proportion, and turn with it.
* **Units** come from the body's size: the stature implied by the skeleton's bone lengths
  (pose-independent) in each candidate unit, the one closest to 1.70 m wins (m, dm, cm, mm,
  inch, foot, CMU's ASF unit of 1/0.45 inch); none between 1.0 and 2.4 m: scaled to 1.70 m.
* **Up axis** is the axis along which the head is above the ankles over the clip (the rest
  pose of Maya-style rigs such as Bandai Namco's and LAFAN1's is not upright). A y-up file
  facing +z ends facing +x in our z-up world (x, y, z -> z, x, y).
* **Alignment** of each BVH joint frame with its SMPL-X part frame is a constant rotation A_k,
  found from the motion itself, so that it works whatever the rest pose: the part's bone
  (towards its child) is matched exactly and the roll about it is fixed by one more direction
  averaged over the clip — the knee or elbow hinge (cross product of the two segments, where
  the limb bends), the shin for the foot, the left-right line of hips and shoulders for the
  trunk, the trunk's up direction for the collars. A part with no such direction (a hand or
  toe without a child, a limb that never bends) keeps its parent's alignment, i.e. the rest
  pose's own roll. Feet are the exception: the foot is aligned so that it lies flat where the
  skeleton stands on it (heel and toe joints down), heading along ankle -> toe, and the toes
  move rigidly with it. Matching the ankle -> toe bone instead tilts the foot by the difference
  between the rig's and SMPL-X's joint placements (heels 4 cm in the floor on Xia's walk), and
  following the rigs' toe joints curls the mannequin's toes into the floor through the swing.
  Measured on the three shared walks (``otr eval``, ground J, Bandai / ganimator / Xia, before
  floor levelling and ankle following): bone-aligned feet 80 / 75 / 78 %, flat feet
  86 / 82 / 84 %, flat rigid feet 87 / 85 / 93 %.
* **Body**: ``fit_shape`` fits the mannequin-x shape coefficients and the pelvis track to the
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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from otr_gym.rotations import matrix_to_quat, quat_from_vector_pairs, quat_normalize, quat_to_matrix
from retarget.inputs.demonstration import Demonstration, InvalidDemonstrationError

UNITS_M: dict[str, float] = {
    "metres": 1.0, "decimetres": 0.1, "centimetres": 0.01, "millimetres": 0.001, "inches": 0.0254,
    "feet": 0.3048, "CMU ASF units (1/0.45 inch)": 0.0254 / 0.45,
}
UNIT_ALIASES = {"m": "metres", "dm": "decimetres", "cm": "centimetres", "mm": "millimetres", "in": "inches",
                "inch": "inches", "ft": "feet", "cmu": "CMU ASF units (1/0.45 inch)"}
TYPICAL_STATURE_M = 1.70
STATURE_RANGE_M = (1.0, 2.4)
UP_AXES = ("x", "y", "z", "-x", "-y", "-z")


class BvhError(InvalidDemonstrationError):
    """A BVH file (or skeleton map) that cannot be used; the message names the file and line or joint."""


# ------------------------------------------------------------------ parsing


@dataclass(frozen=True)
class BvhFile:
    """A parsed BVH file: the skeleton (file units and axes) and the raw MOTION values."""

    path: str
    joint_names: tuple[str, ...]
    parents: tuple[int, ...]  # -1 for the root
    offsets: np.ndarray  # (J, 3) OFFSET of each joint in its parent's frame
    channels: tuple[tuple[str, ...], ...]  # per joint, e.g. ("Xposition", …, "Zrotation", …)
    end_sites: dict[int, np.ndarray]  # joint -> End Site OFFSET (3,) in that joint's frame
    frame_time_s: float
    motion: np.ndarray  # (T, C) one row per frame, channels in HIERARCHY order
    joint_lines: tuple[int, ...] = field(default=())  # line of each joint's declaration

    @property
    def num_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def fps(self) -> float:
        """1 / Frame Time, snapped to a whole rate when within 0.01 % of it (0.0333333 s is 30 Hz)."""
        rate = 1.0 / self.frame_time_s
        return float(round(rate)) if abs(rate - round(rate)) < 1e-4 * rate else rate

    def joint(self, name: str) -> int:
        return self.joint_names.index(name)

    def channel_columns(self) -> list[np.ndarray]:
        """Per joint, the MOTION columns of its channels."""
        counts = [len(c) for c in self.channels]
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int)
        return [np.arange(s, s + n) for s, n in zip(starts, counts, strict=True)]


_CHANNELS = {"Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation"}


class _Lines:
    """Token lines with their 1-based line numbers, for errors that point into the file."""

    def __init__(self, path: str, lines: list[str]) -> None:
        self.path, self.lines, self.i = path, lines, 0

    def fail(self, problem: str, line: int | None = None):
        where = f"{self.path}:{line if line is not None else self.i}"
        raise BvhError(f"{where}: {problem}")

    def next(self, what: str) -> tuple[int, list[str]]:
        while self.i < len(self.lines):
            self.i += 1
            tokens = self.lines[self.i - 1].split()
            if tokens:
                return self.i, tokens
        self.fail(f"file ends where {what} was expected (truncated HIERARCHY?)")


def parse_bvh(path: str | Path) -> BvhFile:
    """Read a BVH file; any problem raises BvhError naming the file, the line and the joint."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise BvhError(f"{path}: cannot read ({exc})") from exc
    src = _Lines(str(path), text.splitlines())
    line, tokens = src.next("HIERARCHY")
    if tokens[0].upper() != "HIERARCHY":
        src.fail(f"expected HIERARCHY, found {tokens[0]!r} (not a BVH file?)", line)
    names, parents, offsets, channels, end_sites, decl_lines = [], [], [], [], {}, []
    line, tokens = src.next("ROOT")
    if tokens[0] != "ROOT" or len(tokens) < 2:
        src.fail(f"expected 'ROOT <name>', found {' '.join(tokens)!r}", line)
    stack: list[int] = []  # open joints; -2 marks an open End Site

    def open_joint(name: str, line: int) -> None:
        if name in names:
            src.fail(f"joint {name!r} declared twice (first on line {decl_lines[names.index(name)]})", line)
        names.append(name)
        parents.append(stack[-1] if stack else -1)
        decl_lines.append(line)
        line, tokens = src.next(f"'{{' after joint {name}")
        if tokens != ["{"]:
            src.fail(f"joint {name}: expected '{{', found {' '.join(tokens)!r}", line)
        line, tokens = src.next(f"OFFSET of joint {name}")
        offsets.append(_offset(src, tokens, line, name))
        line, tokens = src.next(f"CHANNELS of joint {name}")
        if tokens[0] != "CHANNELS" or len(tokens) < 2 or not tokens[1].isdigit():
            src.fail(f"joint {name}: expected 'CHANNELS <count> <names>', found {' '.join(tokens)!r}", line)
        listed = tuple(tokens[2:])
        if int(tokens[1]) != len(listed):
            src.fail(f"joint {name}: CHANNELS declares {tokens[1]} channels but lists {len(listed)} "
                     f"({' '.join(listed)})", line)
        unknown = [c for c in listed if c not in _CHANNELS]
        if unknown:
            src.fail(f"joint {name}: unknown channel(s) {unknown} (expected X/Y/Z position/rotation)", line)
        channels.append(listed)
        stack.append(len(names) - 1)

    open_joint(" ".join(tokens[1:]), line)
    while stack:
        line, tokens = src.next(f"'}}' closing joint {names[stack[-1]] if stack[-1] >= 0 else 'End Site'}")
        if tokens[0] == "JOINT" and len(tokens) >= 2:
            if stack[-1] < 0:
                src.fail("a JOINT inside an End Site", line)
            open_joint(" ".join(tokens[1:]), line)
        elif tokens[0] == "End" and stack[-1] >= 0:
            owner = stack[-1]
            _, brace = src.next("'{' after End Site")
            if brace != ["{"]:
                src.fail(f"End Site of joint {names[owner]}: expected '{{'", src.i)
            offset_line, offset_tokens = src.next(f"OFFSET of the End Site of joint {names[owner]}")
            end_sites[owner] = _offset(src, offset_tokens, offset_line, f"{names[owner]} (End Site)")
            stack.append(-2)
        elif tokens == ["}"]:
            stack.pop()
        else:
            src.fail(f"unexpected {' '.join(tokens)!r} in the HIERARCHY "
                     f"(inside {names[stack[-1]] if stack[-1] >= 0 else 'an End Site'})", line)
    _, tokens = src.next("MOTION")
    if tokens[0] != "MOTION":
        src.fail(f"expected MOTION after the HIERARCHY, found {' '.join(tokens)!r}", src.i)
    line, tokens = src.next("'Frames: <count>'")
    if len(tokens) != 2 or tokens[0] != "Frames:" or not tokens[1].isdigit():
        src.fail(f"expected 'Frames: <count>', found {' '.join(tokens)!r}", line)
    frames = int(tokens[1])
    line, tokens = src.next("'Frame Time: <seconds>'")
    if len(tokens) != 3 or tokens[:2] != ["Frame", "Time:"]:
        src.fail(f"expected 'Frame Time: <seconds>', found {' '.join(tokens)!r}", line)
    try:
        frame_time = float(tokens[2])
    except ValueError:
        src.fail(f"Frame Time {tokens[2]!r} is not a number", line)
    if not (math.isfinite(frame_time) and frame_time > 0):
        src.fail(f"Frame Time must be a positive number of seconds, got {tokens[2]}", line)
    if frames < 1:
        src.fail("MOTION declares 0 frames", line)
    width = sum(len(c) for c in channels)
    motion = _read_motion(src, frames, width, names, channels)
    return BvhFile(path=str(path), joint_names=tuple(names), parents=tuple(parents),
                   offsets=np.array(offsets, dtype=np.float64), channels=tuple(channels), end_sites=end_sites,
                   frame_time_s=frame_time, motion=motion, joint_lines=tuple(decl_lines))


def _offset(src: _Lines, tokens: list[str], line: int, name: str) -> np.ndarray:
    if tokens[0] != "OFFSET" or len(tokens) != 4:
        src.fail(f"joint {name}: expected 'OFFSET x y z', found {' '.join(tokens)!r}", line)
    try:
        value = np.array([float(t) for t in tokens[1:]])
    except ValueError:
        src.fail(f"joint {name}: OFFSET {' '.join(tokens[1:])!r} is not three numbers", line)
    if not np.isfinite(value).all():
        src.fail(f"joint {name}: non-finite OFFSET {' '.join(tokens[1:])}", line)
    return value


def _column_owner(names, channels, column: int) -> str:
    """'joint <name>, <channel>' of a MOTION column (0-based)."""
    for name, listed in zip(names, channels, strict=True):
        if column < len(listed):
            return f"joint {name}, {listed[column]}"
        column -= len(listed)
    return "beyond the declared channels"


def _read_motion(src: _Lines, frames: int, width: int, names, channels) -> np.ndarray:
    rows: list[str] = []
    row_lines: list[int] = []
    while len(rows) < frames and src.i < len(src.lines):
        src.i += 1
        text = src.lines[src.i - 1]
        if text.strip():
            rows.append(text)
            row_lines.append(src.i)
    if len(rows) < frames:
        src.fail(f"MOTION declares {frames} frames but the file ends after {len(rows)} (truncated MOTION block)",
                 src.i)
    counts = [len(r.split()) for r in rows]
    for k, count in enumerate(counts):
        if count != width:
            last = " (the file's last line: truncated?)" if k == len(rows) - 1 and count < width else ""
            src.fail(f"frame {k} has {count} values but the HIERARCHY declares {width} channels{last}", row_lines[k])
    tokens = " ".join(rows).split()
    try:
        values = np.array(tokens, dtype=np.float64)
    except ValueError:
        for k, row in enumerate(rows):
            for c, token in enumerate(row.split()):
                try:
                    float(token)
                except ValueError:
                    owner = _column_owner(names, channels, c)
                    src.fail(f"frame {k}, column {c + 1} ({owner}): {token!r} is not a number", row_lines[k])
        raise
    values = values.reshape(frames, width)
    bad = np.argwhere(~np.isfinite(values))
    if len(bad):
        k, c = (int(i) for i in bad[0])
        src.fail(f"frame {k}, column {c + 1} ({_column_owner(names, channels, c)}): non-finite value "
                 f"{rows[k].split()[c]!r}", row_lines[k])
    return values


# ------------------------------------------------------------------ forward kinematics


def _axis_rotations(axis: str, degrees: np.ndarray) -> np.ndarray:
    """Rotation matrices (T, 3, 3) about a coordinate axis 'X' | 'Y' | 'Z'."""
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(a), np.zeros_like(a)
    rows = {"X": [[one, zero, zero], [zero, c, -s], [zero, s, c]],
            "Y": [[c, zero, s], [zero, one, zero], [-s, zero, c]],
            "Z": [[c, -s, zero], [s, c, zero], [zero, zero, one]]}[axis]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def local_transforms(bvh: BvhFile, frames=slice(None)) -> tuple[np.ndarray, np.ndarray]:
    """Per joint local translation (T, J, 3) and rotation (T, J, 3, 3), file units."""
    motion = bvh.motion[frames]
    count, joints = len(motion), len(bvh.joint_names)
    trans = np.broadcast_to(bvh.offsets, (count, joints, 3)).copy()
    rot = np.broadcast_to(np.eye(3), (count, joints, 3, 3)).copy()
    for j, (listed, cols) in enumerate(zip(bvh.channels, bvh.channel_columns(), strict=True)):
        for name, col in zip(listed, cols, strict=True):
            if name.endswith("position"):
                trans[:, j, "XYZ".index(name[0])] = motion[:, col]
            else:
                rot[:, j] = rot[:, j] @ _axis_rotations(name[0], motion[:, col])
    return trans, rot


def world_transforms(bvh: BvhFile, frames=slice(None), rest: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """World joint positions (T, J, 3) and rotations (T, J, 3, 3) in the file's units and axes.

    ``rest=True``: the rest pose (OFFSETs, no rotation; one frame).
    """
    if rest:
        trans, rot = bvh.offsets[None].copy(), np.broadcast_to(np.eye(3), (1, len(bvh.joint_names), 3, 3)).copy()
    else:
        trans, rot = local_transforms(bvh, frames)
    pos_w, rot_w = np.empty_like(trans), np.empty_like(rot)
    for j, parent in enumerate(bvh.parents):  # parents precede children in a BVH file
        if parent < 0:
            pos_w[:, j], rot_w[:, j] = trans[:, j], rot[:, j]
        else:
            pos_w[:, j] = pos_w[:, parent] + np.einsum("tab,tb->ta", rot_w[:, parent], trans[:, j])
            rot_w[:, j] = rot_w[:, parent] @ rot[:, j]
    return pos_w, rot_w


# ------------------------------------------------------------------ skeleton families

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
                       "Give --skeleton-map YAML mapping SMPL-X parts to joint names (retarget/inputs/bvh.py)")
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


# ------------------------------------------------------------------ alignment to SMPL-X parts


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


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


@dataclass
class _Skeleton:
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


def _mapped_skeleton(bvh: BvhFile, mapping: dict[str, JointRef], to_world: np.ndarray, scale: float) -> _Skeleton:
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
    return _Skeleton(joint_of_part, part_pos, rot[:, joint_of_part], tips, missing)


#: The joint each part's bone points to (matched exactly); None: the part has no child joint. The
#: spine parts point to the neck: SMPL-X's short spine segments lean up to 30° from the trunk
#: line, and rigs place their spine joints differently.
_PRIMARY = {
    "Pelvis": None, "L_Hip": "L_Knee", "R_Hip": "R_Knee", "Spine1": "Neck", "L_Knee": "L_Ankle",
    "R_Knee": "R_Ankle", "Spine2": "Neck", "L_Ankle": "L_Foot", "R_Ankle": "R_Foot", "Spine3": "Neck",
    "L_Foot": None, "R_Foot": None, "Neck": "Head", "L_Collar": "L_Shoulder", "R_Collar": "R_Shoulder",
    "Head": None, "L_Shoulder": "L_Elbow", "R_Shoulder": "R_Elbow", "L_Elbow": "L_Wrist", "R_Elbow": "R_Wrist",
    "L_Wrist": None, "R_Wrist": None,
}
#: SMPL-X rest-frame direction of a tip beyond a childless part (x left, y up, z forward).
_TIP_DIRECTION = {"L_Wrist": (1.0, 0.0, 0.0), "R_Wrist": (-1.0, 0.0, 0.0), "L_Foot": (0.0, 0.0, 1.0),
                  "R_Foot": (0.0, 0.0, 1.0), "Head": (0.0, 1.0, 0.0)}
#: Ridge of the shape fit (``fit_shape``; m² per unit coefficient²). BVH joints are placed by each
#: rig's own conventions, not SMPL-X's, so an exact fit drives coefficients to ±7 (a distorted
#: figure) to chase those placements; 1e-5 keeps them within ±4 for about 1 cm more mean
#: joint error on the three shared walks (1e-6: 2.0–3.5 cm, |β| ≤ 7.5; 1e-5: 2.8–4.3 cm, |β| ≤ 3.8).
SHAPE_RIDGE_M2 = 1e-5
#: A hinge cue counts when the mean |sin| of the bend it is taken from exceeds this.
MIN_HINGE_SIN = 0.05


def _alignments(sk: _Skeleton) -> tuple[np.ndarray, dict[str, str]]:
    """A_k (22, 3, 3): SMPL-X part frame -> BVH joint frame, so part rotation = W_j(k)(t) A_k.

    Returns the matrices and, per part, which direction fixed its roll (module docstring)."""
    from retarget.inputs.human import PART_NAMES, PART_PARENTS, shape_basis

    rest = shape_basis().rest_joints
    idx = {n: i for i, n in enumerate(PART_NAMES)}
    p, w = sk.pos_w, sk.rot_w

    def local(k: int, v_w: np.ndarray) -> np.ndarray:  # world vectors (T, 3) -> joint frame of part k
        return np.einsum("tba,tb->ta", w[:, k], v_w)

    def bone(a: str, b: str) -> np.ndarray:
        return p[:, idx[b]] - p[:, idx[a]]

    def rest_dir(a: str, b: str) -> np.ndarray:
        return _unit(rest[idx[b]] - rest[idx[a]])

    lateral_w = _unit(_unit(bone("R_Hip", "L_Hip")) + _unit(bone("R_Shoulder", "L_Shoulder")))
    trunk_up_w = _unit(bone("Spine3", "Head"))

    def hinge(upper: tuple[str, str], lower: tuple[str, str]) -> np.ndarray:
        return np.cross(_unit(bone(*upper)), _unit(bone(*lower)))

    knee = {s: hinge((f"{s}_Hip", f"{s}_Knee"), (f"{s}_Knee", f"{s}_Ankle")) for s in "LR"}
    elbow = {s: hinge((f"{s}_Shoulder", f"{s}_Elbow"), (f"{s}_Elbow", f"{s}_Wrist")) for s in "LR"}
    out = np.zeros((len(PART_NAMES), 3, 3))
    how: dict[str, str] = {}
    for k, part in enumerate(PART_NAMES):  # parents first
        side = part[0] if part[:2] in ("L_", "R_") else ""
        primary = _PRIMARY[part]
        if part.endswith(("_Ankle", "_Foot")):
            out[k], how[part] = _flat_foot_alignment(p, w, side, k, rest), "flat in stance, heading ankle -> toe"
            continue
        if part == "Pelvis":
            a_from, a_w = rest_dir("R_Hip", "L_Hip"), bone("R_Hip", "L_Hip")
        elif primary is not None:
            # the first descendant along the chain that is not at the same place (Xia's Neck)
            target = primary
            while np.linalg.norm(bone(part, target), axis=-1).mean() < 1e-3 and _PRIMARY.get(target):
                target = _PRIMARY[target]
            a_from, a_w = rest_dir(part, target), bone(part, target)
        elif part in sk.tips:
            a_from, a_w = np.array(_TIP_DIRECTION[part]), sk.tips[part] - p[:, k]
        else:
            out[k] = out[PART_PARENTS[k]]
            how[part] = "inherited (no tip)"
            continue
        cue = None
        if part == "Pelvis":
            cue = (rest_dir("Pelvis", "Spine3"), bone("Pelvis", "Spine3"), "trunk up")
        elif part.startswith(("Spine", "Neck", "Head")):
            cue = (np.array([1.0, 0.0, 0.0]), lateral_w, "left-right line")
        elif part.endswith(("_Hip", "_Knee")):
            h = knee[side]
            if np.linalg.norm(h.mean(axis=0)) > MIN_HINGE_SIN:
                cue = (np.array([1.0, 0.0, 0.0]), h, "knee hinge")
            else:
                cue = (np.array([1.0, 0.0, 0.0]), lateral_w, "left-right line")
        elif part.endswith(("_Ankle", "_Foot")):
            cue = (rest_dir(f"{side}_Ankle", f"{side}_Knee"), bone(f"{side}_Ankle", f"{side}_Knee"), "shin")
        elif part.endswith("_Collar"):
            cue = (rest_dir("Spine3", "Head"), trunk_up_w, "trunk up")
        elif part.endswith(("_Shoulder", "_Elbow", "_Wrist")):
            h = elbow[side]
            if np.linalg.norm(h.mean(axis=0)) > MIN_HINGE_SIN:
                cue = (np.array([0.0, -1.0 if side == "L" else 1.0, 0.0]), h, "elbow hinge")
        a_to = _unit(local(k, _unit(a_w)).mean(axis=0))
        if cue is None:
            # keep the parent's roll: the swing from the inherited frame onto this bone
            inherited = out[PART_PARENTS[k]]
            b_from = np.cross(a_from, [0.0, 0.0, 1.0]) if abs(a_from[2]) < 0.9 else np.cross(a_from, [1.0, 0, 0])
            b_to = inherited @ b_from
            how[part] = "bone, roll inherited"
        else:
            b_from, b_w, label = cue
            b_to = local(k, b_w).mean(axis=0)
            how[part] = f"bone, roll from {label}"
        out[k] = quat_to_matrix(quat_from_vector_pairs(a_from, b_from, a_to, b_to))
    return out, how


#: Flat-foot frames: ankle and toe joints both within this height of their lowest (5th percentile)
#: heights, and the toe among the slower half of those frames.
STANCE_BAND_M = 0.02


def _flat_foot_alignment(p: np.ndarray, w: np.ndarray, side: str, k: int, rest: np.ndarray) -> np.ndarray:
    """A_k for a foot part (ankle or toes): the rotation that makes the SMPL-X foot lie flat in
    the stance frames, heading where the skeleton's ankle -> toe points.

    Matching the ankle -> toe bone instead would tilt the foot by the difference between the
    rig's and SMPL-X's joint placements (Xia's toe joint is 10° below its ankle, SMPL-X's 26°:
    heels 4 cm in the floor). Chordal mean over the stance frames of W_j(t)ᵀ R_flat(t).
    """
    from retarget.inputs.human import PART_NAMES, SMPLX_REST_QUAT_W

    ankle, toe = PART_NAMES.index(f"{side}_Ankle"), PART_NAMES.index(f"{side}_Foot")
    low = np.ones(len(p), dtype=bool)
    for joint in (ankle, toe):  # heel and toes down: the foot is flat
        height = p[:, joint, 2]
        low &= height <= np.percentile(height, 5) + STANCE_BAND_M
    speed = np.linalg.norm(np.gradient(p[:, toe, :2], axis=0), axis=-1)  # m per frame
    still = speed <= np.percentile(speed[low], 50) if low.any() else low
    stance = low & still if (low & still).sum() >= 2 else np.ones(len(p), dtype=bool)
    q0 = quat_to_matrix(SMPLX_REST_QUAT_W)
    rest_heading = (q0 @ (rest[toe] - rest[ankle]))[:2]
    heading = (p[stance, toe] - p[stance, ankle])[:, :2]
    yaw = np.arctan2(heading[:, 1], heading[:, 0]) - np.arctan2(rest_heading[1], rest_heading[0])
    c, s = np.cos(yaw), np.sin(yaw)
    rz = np.zeros((len(yaw), 3, 3))
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = c, -s, s, c, 1.0
    m = np.einsum("tba,tbc->ac", w[stance, k], rz @ q0)
    u, _, vt = np.linalg.svd(m)
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


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
    normal = _unit(np.array([-slope * direction[0], -slope * direction[1], 1.0]))
    axis = np.cross(normal, [0.0, 0.0, 1.0])
    turn = quat_from_rotvec(_unit(axis) * np.radians(tilt))
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

    sk = _mapped_skeleton(bvh, mapping, to_world, scale)
    align, how = _alignments(sk)
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
