"""The clip library of a run: what ``--reference`` names, which clips load, which are skipped.

``--reference`` takes one or more items, each a reference ``.npz``, a folder of them or a
clip-list file (``.txt``/``.list``, ``otr_gym.reference.clip_entries``). The lists are read
once, every clip is loaded once and prepared for the environment's command
(``envs.mdp.motion.prepared_references``: tracked bodies present, resampled to the policy rate,
long enough): the library's ``clips`` (``envs.clips.PreparedClips``) go to the environment
as they are. A clip that fails is reported by name with the reason and skipped; a library left
without clips raises. The run records both lists (``config.yaml``: ``reference_info.clips`` /
``reference_info.skipped``).

Clips of one library may differ in length and frame rate: each is resampled to 50 fps at
load. OTR-G1-BoxTrack-v0 simulates one object set, so its library must share it: clips whose
objects differ are refused when the environment is built (``envs.objects.scene_objects``).
A clip may come with a terrain mesh (``env.terrain.meshes`` or ``terrain=`` on its clip-list
line; ``envs.terrain``): ``with_terrain`` puts both into the run's env config.
"""

from __future__ import annotations

import sys
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from envs.clips import PreparedClips
from envs.config import CommandCfg, load_env_config
from envs.mdp.motion import prepared_references
from envs.terrain import listed_terrain, meshes_for_clips, terrain_meshes
from otr_gym.reference import InvalidReferenceError, Reference, clip_entries

#: What a broken clip file can raise while it is read and prepared.
_LOAD_ERRORS = (InvalidReferenceError, OSError, ValueError, KeyError)  # NpzError is a ValueError


@dataclass(frozen=True)
class SkippedClip:
    path: str
    error: str


@dataclass(frozen=True)
class ClipLibrary:
    spec: tuple[str, ...]  # the --reference items as given, made absolute
    clips: PreparedClips  # clips that load, prepared for the environment, with their clip-list terrain
    skipped: tuple[SkippedClip, ...]

    @property
    def references(self) -> tuple[Reference, ...]:
        """The clips that load, prepared (50 fps), in library order."""
        return self.clips.references

    @property
    def name(self) -> str:
        """Run-folder name part: the item's stem (a folder's name), ``<first>+<n>`` for several."""
        stems = [Path(s).name if Path(s).is_dir() else Path(s).stem for s in self.spec]
        return stems[0] if len(stems) == 1 else f"{stems[0]}+{len(stems) - 1}"

    @property
    def source(self) -> str | list[str]:
        """What to pass to the environment again (evaluation, resume): the spec."""
        return self.spec[0] if len(self.spec) == 1 else list(self.spec)

    def info(self) -> dict:
        """The run record's ``reference_info``."""
        return {"name": self.name, "path": self.source, "clips": [r.source for r in self.references],
                "labels": clip_labels([r.source for r in self.references]),
                "skipped": [{"clip": s.path, "error": s.error} for s in self.skipped]}


def with_terrain(env_overrides: dict, library: ClipLibrary, clips: Sequence[str] | None = None) -> dict:
    """``env_overrides`` with ``terrain.meshes`` completed by the ``terrain=`` options of the
    library's clip lists and every mesh path made absolute: what the run's config.yaml records,
    so that resume, evaluation, play and the sim robot simulate the same terrain. Given
    ``clips`` (sources), only the entries that name one of them are kept (evaluating or playing
    part of a library)."""
    terrain = dict(env_overrides.get("terrain") or {})
    meshes = terrain_meshes(terrain.get("meshes") or {}, library.clips.listed_meshes)
    if clips is not None:
        meshes = meshes_for_clips(meshes, clips)
    if not meshes and "meshes" not in terrain:
        return env_overrides
    return {**env_overrides, "terrain": {**terrain, "meshes": meshes}}


def reference_spec(reference: str | Path | Sequence[str | Path]) -> tuple[str, ...]:
    items = [reference] if isinstance(reference, (str, Path)) else list(reference)
    if not items:
        raise InvalidReferenceError("no reference given")
    return tuple(str(Path(i).expanduser().resolve()) for i in items)


def load_library(reference: str | Path | Sequence[str | Path], task: str, env_overrides: dict | None = None,
                 report: bool = True) -> ClipLibrary:
    """``prepare_library`` for the command of ``task``'s env config with ``env_overrides``."""
    return prepare_library(reference, load_env_config(task, overrides=env_overrides or None).command, report)


def prepare_library(reference: str | Path | Sequence[str | Path], command: CommandCfg,
                    report: bool = True) -> ClipLibrary:
    """Every clip named by ``reference`` prepared for ``command``'s tracked bodies and rate,
    each clip list read and each clip loaded once; clips that fail are skipped with their
    reason (printed to stderr with ``report``)."""
    spec = reference_spec(reference)
    entries = [e for item in spec for e in clip_entries(item)]
    good: list[Reference] = []
    skipped: list[SkippedClip] = []
    for entry in entries:
        try:
            good.extend(prepared_references(entry.path, command.tracked_bodies, command.fps, command.min_clip_frames))
        except _LOAD_ERRORS as exc:
            message = str(exc) if str(entry.path) in str(exc) else f"{entry.path}: {exc}"
            skipped.append(SkippedClip(str(entry.path), message))
    if report:
        for s in skipped:
            print(f"skipped clip: {s.error}", file=sys.stderr)
    if not good:
        raise InvalidReferenceError(f"no clip of {', '.join(spec)} could be loaded ({len(skipped)} skipped)")
    return ClipLibrary(spec, PreparedClips.of(good, listed_terrain(entries), command), tuple(skipped))


def clip_labels(sources: Sequence[str]) -> list[str]:
    """Short unique names of clips for logs and tables: the file stem, prefixed by its folder
    where two stems collide, suffixed ``#k`` if still ambiguous."""
    stems = [Path(s).stem for s in sources]
    counts = Counter(stems)
    labels = [f"{Path(s).parent.name}/{stem}" if counts[stem] > 1 else stem for s, stem in zip(sources, stems)]
    counts = Counter(labels)
    seen: Counter = Counter()
    out = []
    for label in labels:
        seen[label] += 1
        out.append(f"{label}#{seen[label]}" if counts[label] > 1 else label)
    return out
