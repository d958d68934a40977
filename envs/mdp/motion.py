"""A library of reference clips, concatenated into flat device tensors.

Every clip is loaded with ``otr_gym.reference.Reference`` (ours, Holosoma's and mjlab's npz
layouts), resampled to the policy rate and given velocities that are finite differences of
its poses (this also discards Holosoma's stored ``body_ang_vel_w``, which is R·ω rather than
ω). Frame ``t`` of clip ``c`` lives at row ``clip_start[c] + t`` of every array.

Only the tracked bodies are kept, in ``body_names`` order (selected by name, so files with
extra bodies such as 'world' or an object load unchanged). Frames are world; quaternions wxyz.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch

from otr_gym.reference import InvalidReferenceError, Reference, list_references

ReferenceSource = str | Path | Reference | Sequence[str | Path | Reference]


@dataclass(frozen=True)
class MotionLibrary:
    names: tuple[str, ...]  # source of each clip (file path or '<memory>')
    fps: float
    body_names: tuple[str, ...]
    clip_start: torch.Tensor  # (C,) long, first row of each clip
    clip_length: torch.Tensor  # (C,) long, frames per clip
    root_pos_w: torch.Tensor  # (F, 3) m
    root_quat_w: torch.Tensor  # (F, 4) wxyz
    root_lin_vel_w: torch.Tensor  # (F, 3) m/s
    root_ang_vel_w: torch.Tensor  # (F, 3) rad/s, world frame
    joint_pos: torch.Tensor  # (F, 29) rad, G1 order
    joint_vel: torch.Tensor  # (F, 29) rad/s
    body_pos_w: torch.Tensor  # (F, K, 3)
    body_quat_w: torch.Tensor  # (F, K, 4)
    body_lin_vel_w: torch.Tensor  # (F, K, 3)
    body_ang_vel_w: torch.Tensor  # (F, K, 3)

    @property
    def num_clips(self) -> int:
        return len(self.names)

    @property
    def device(self) -> torch.device:
        return self.joint_pos.device

    def to(self, device: str | torch.device) -> MotionLibrary:
        """The same library with every tensor on ``device``."""
        return replace(self, **{f.name: getattr(self, f.name).to(device) for f in fields(self)
                                if isinstance(getattr(self, f.name), torch.Tensor)})

    def qpos(self, rows: torch.Tensor) -> torch.Tensor:
        """(…, 36) MuJoCo qpos [root xyz, root wxyz, joints] of library rows."""
        return torch.cat([self.root_pos_w[rows], self.root_quat_w[rows], self.joint_pos[rows]], dim=-1)

    @classmethod
    def load(cls, source: ReferenceSource, body_names: Sequence[str], fps: float = 50.0,
             min_clip_frames: int = 2, device: str | torch.device = "cpu") -> MotionLibrary:
        """Load a file, a folder of ``*.npz``, ``Reference`` objects, or a list of those.

        Raises ``InvalidReferenceError`` naming the file for a missing/unreadable file, a
        wrong joint set, NaN, missing tracked bodies, or a clip shorter than ``min_clip_frames``
        after resampling.
        """
        return cls.from_references(prepared_references(source, body_names, fps, min_clip_frames), body_names, fps,
                                   device)

    @classmethod
    def from_references(cls, refs: Sequence[Reference], body_names: Sequence[str], fps: float,
                        device: str | torch.device = "cpu") -> MotionLibrary:
        """The library of references already prepared by ``prepared_references``."""
        lengths = [r.num_frames for r in refs]
        starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])

        def cat(get) -> torch.Tensor:
            return torch.as_tensor(np.concatenate([get(r) for r in refs]), dtype=torch.float32, device=device)

        def bodies(r: Reference, arr: np.ndarray) -> np.ndarray:
            return arr[:, r.body_index(body_names)]

        return cls(
            names=tuple(r.source for r in refs), fps=float(fps), body_names=tuple(body_names),
            clip_start=torch.as_tensor(starts, dtype=torch.long, device=device),
            clip_length=torch.as_tensor(lengths, dtype=torch.long, device=device),
            root_pos_w=cat(lambda r: r.root_pos_w), root_quat_w=cat(lambda r: r.root_quat_w),
            root_lin_vel_w=cat(lambda r: r.joint_vel[:, :3]), root_ang_vel_w=cat(lambda r: r.joint_vel[:, 3:6]),
            joint_pos=cat(lambda r: r.dof_pos), joint_vel=cat(lambda r: r.dof_vel),
            body_pos_w=cat(lambda r: bodies(r, r.body_pos_w)), body_quat_w=cat(lambda r: bodies(r, r.body_quat_w)),
            body_lin_vel_w=cat(lambda r: bodies(r, r.body_lin_vel_w)),
            body_ang_vel_w=cat(lambda r: bodies(r, r.body_ang_vel_w)),
        )


def prepared_references(source: ReferenceSource, body_names: Sequence[str], fps: float = 50.0,
                        min_clip_frames: int = 2) -> list[Reference]:
    """Every clip of ``source`` loaded, checked, resampled to ``fps`` with finite-difference
    velocities (objects included), in library order."""
    return [_prepared(r, body_names, fps, min_clip_frames) for r in _expand(source)]


def _expand(source: ReferenceSource) -> list[Reference | Path]:
    if isinstance(source, (str, Path)):
        return list(list_references(source))
    if isinstance(source, Reference):
        return [source]
    items: list[Reference | Path] = []
    for s in source:
        items.extend(_expand(s))
    if not items:
        raise InvalidReferenceError("no reference clips given")
    return items


def _prepared(item: Reference | Path, body_names: Sequence[str], fps: float, min_clip_frames: int) -> Reference:
    ref = item if isinstance(item, Reference) else Reference.load(item)
    ref.body_index(body_names)  # raises naming the file if a tracked body is missing
    ref = ref.resampled(fps).with_recomputed_velocities()
    if ref.num_frames < min_clip_frames:
        raise InvalidReferenceError(
            f"{ref.source}: too short for tracking: {ref.num_frames} frames at {fps:g} fps "
            f"({ref.duration_s:.2f} s), need at least {min_clip_frames}")
    return ref
