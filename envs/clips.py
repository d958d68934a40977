"""The clips of an environment, read and prepared once: clip lists and folders expanded, every
file loaded, checked and resampled for the tracking MDP (``envs.mdp.motion``), then placed on
their terrain (``envs.terrain``). ``otr train`` prepares them once (``agents.library``) and hands
them to the environment, which then reads nothing again."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from envs.config import CommandCfg, TrackEnvCfg
from envs.mdp.motion import ReferenceSource, prepared_references
from envs.terrain import SceneTerrain, listed_terrain, place_terrain, terrain_meshes
from otr_gym.reference import ClipEntry, InvalidReferenceError, Reference, clip_entries


@dataclass(frozen=True)
class PreparedClips:
    """A clip library read and prepared once for the tracking MDP: every clip loaded, checked
    and resampled to ``fps`` with finite-difference velocities (``envs.mdp.motion``), in
    library order, with the terrain meshes its clip lists gave (``terrain=``). ``make_task``
    takes it as ``reference`` and only places it on its terrain: nothing is read again."""

    references: tuple[Reference, ...]
    listed_meshes: dict[str, str]  # clip path -> absolute mesh path, from clip-list lines
    # what the clips were prepared for (``CommandCfg``): a config asking for other bodies, rate
    # or minimum length must not be handed these
    tracked_bodies: tuple[str, ...]
    fps: float  # frames per second
    min_clip_frames: int

    @classmethod
    def of(cls, references: Sequence[Reference], listed_meshes: dict[str, str], command: CommandCfg) -> PreparedClips:
        """Clips already prepared for ``command`` (``prepared_references``), with their clip-list meshes."""
        return cls(tuple(references), dict(listed_meshes), tuple(command.tracked_bodies), float(command.fps),
                   int(command.min_clip_frames))

    def check(self, command: CommandCfg) -> None:
        """Raise ``ValueError`` naming what differs unless the clips were prepared for ``command``."""
        wanted = {"tracked_bodies": tuple(command.tracked_bodies), "fps": float(command.fps),
                  "min_clip_frames": int(command.min_clip_frames)}
        differ = [f"{key} {getattr(self, key)} (clips) vs {value} (environment)"
                  for key, value in wanted.items() if getattr(self, key) != value]
        if differ:
            raise ValueError(f"clips prepared for another command: {'; '.join(differ)}; prepare them with the "
                             "environment's config (envs.clips.prepare_clips)")


def prepare_clips(reference: ReferenceSource, command: CommandCfg) -> PreparedClips:
    """Every clip of ``reference`` read once (clip lists parsed once, each file loaded once) and
    prepared for ``command``; the first bad clip raises ``InvalidReferenceError`` naming its file."""
    items = _clip_items(reference)
    refs = prepared_references([i if isinstance(i, Reference) else i.path for i in items], command.tracked_bodies,
                               command.fps, command.min_clip_frames)
    return PreparedClips.of(refs, listed_terrain(i for i in items if isinstance(i, ClipEntry)), command)


def _clip_items(reference: ReferenceSource) -> list[ClipEntry | Reference]:
    """The clips ``reference`` names, in library order: its clip lists and folders expanded."""
    if isinstance(reference, Reference):
        return [reference]
    if isinstance(reference, (str, Path)):
        return clip_entries(reference)
    items = [item for part in reference for item in _clip_items(part)]
    if not items:
        raise InvalidReferenceError("no reference clips given")
    return items


def placed_clips(reference: ReferenceSource | PreparedClips,
                 cfg: TrackEnvCfg) -> tuple[list[Reference], SceneTerrain]:
    """(the clips of ``reference``, prepared for ``cfg.command`` unless they come prepared, and
    shifted to their terrain origins; the scene's terrain) for ``cfg.terrain`` and the meshes
    of the clip lists."""
    clips = reference if isinstance(reference, PreparedClips) else prepare_clips(reference, cfg.command)
    clips.check(cfg.command)
    return place_terrain(clips.references, cfg.terrain, terrain_meshes(cfg.terrain.meshes, clips.listed_meshes))
