"""BVH files: the parser and the skeleton's forward kinematics (file units and axes).

Why our own parser: ``bvhio`` (the maintained PyPI reader) loops forever on a truncated MOTION
block (its line reader never sees the end of the file), pins exact versions of its two
dependencies and names neither file nor joint in its errors. This one is small, reads the
MOTION block with one NumPy conversion, and every error names the file, the line and the joint.

Syntax: a joint's ``{`` may open on its own line or at the end of the declaration line
(``ROOT Hips {``, ``JOINT Spine {``, ``End Site {``), as many exporters write it.

Semantics (the common reading of the format, as Blender's and MotionBuilder's importers do):
a joint's local transform is a translation — its OFFSET, replaced axis by axis by its position
channels when it has any (Bandai Namco files give every joint six channels) — followed by the
rotation channels composed in the listed order (``Zrotation Xrotation Yrotation`` is
Rz·Rx·Ry acting on column vectors), angles in degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from retarget.inputs.demonstration import InvalidDemonstrationError


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
    words, braced = _declaration(tokens)
    if words[0] != "ROOT" or len(words) < 2:
        src.fail(f"expected 'ROOT <name>', found {' '.join(tokens)!r}", line)
    stack: list[int] = []  # open joints; -2 marks an open End Site

    def open_joint(name: str, line: int, braced: bool) -> None:
        if name in names:
            src.fail(f"joint {name!r} declared twice (first on line {decl_lines[names.index(name)]})", line)
        names.append(name)
        parents.append(stack[-1] if stack else -1)
        decl_lines.append(line)
        if not braced:
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

    open_joint(" ".join(words[1:]), line, braced)
    while stack:
        line, tokens = src.next(f"'}}' closing joint {names[stack[-1]] if stack[-1] >= 0 else 'End Site'}")
        words, braced = _declaration(tokens)
        if words[0] == "JOINT" and len(words) >= 2:
            if stack[-1] < 0:
                src.fail("a JOINT inside an End Site", line)
            open_joint(" ".join(words[1:]), line, braced)
        elif words[0] == "End" and stack[-1] >= 0:
            owner = stack[-1]
            if not braced:
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


def _declaration(tokens: list[str]) -> tuple[list[str], bool]:
    """The words of a ``ROOT``/``JOINT``/``End Site`` line without a trailing ``{``, and whether
    it had one (``ROOT Hips {``, ``JOINT Spine{``: the block opens on the declaration's line)."""
    if len(tokens) > 1 and tokens[-1] == "{":
        return tokens[:-1], True
    if len(tokens) > 1 and tokens[-1].endswith("{"):
        return [*tokens[:-1], tokens[-1][:-1]], True
    return tokens, False


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
