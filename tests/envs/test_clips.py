"""``envs.clips.PreparedClips``: a clip library read and prepared once (``prepare_clips``,
or ``agents.library`` for ``otr train``) that the environment takes as it is. Handing it over
builds the same task as handing over the files; clips prepared for another command are refused."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch
import trimesh

from agents.procedural import WalkSpec, walking_reference
from envs.clips import prepare_clips
from envs.config import load_track_config
from envs.tracking import make_task

PLATFORM_TOP_M = 0.05


@pytest.fixture(scope="module")
def terrain_listing(tmp_path_factory) -> Path:
    """clips.txt: a walk recorded at 30 fps (resampled to 50 at load) and the same walk raised
    onto a 5 cm platform, ``terrain=platform.obj``."""
    folder = tmp_path_factory.mktemp("listing")
    walk = walking_reference(WalkSpec(steps=4, fps=30.0))
    walk.save(folder / "flat_walk.npz")
    walk.translated([0.0, 0.0, PLATFORM_TOP_M]).save(folder / "platform_walk.npz")
    platform = trimesh.creation.box(extents=(4.0, 2.0, 0.15))
    platform.apply_translation((0.5, 0.0, PLATFORM_TOP_M - 0.075))
    platform.export(folder / "platform.obj")
    listing = folder / "clips.txt"
    listing.write_text("flat_walk.npz\nplatform_walk.npz  terrain=platform.obj\n")
    return listing


def test_prepared_clips_carry_the_clip_lists_terrain(terrain_listing):
    clips = prepare_clips(terrain_listing, load_track_config().command)
    assert [Path(r.source).name for r in clips.references] == ["flat_walk.npz", "platform_walk.npz"]
    assert {r.fps for r in clips.references} == {50.0}
    assert clips.listed_meshes == {str(terrain_listing.parent / "platform_walk.npz"):
                                   str(terrain_listing.parent / "platform.obj")}


def test_a_task_built_from_prepared_clips_is_the_task_built_from_the_files(terrain_listing):
    from_files = make_task(terrain_listing, 2, "mujoco", "cpu", evaluation=True)
    prepared = make_task(prepare_clips(terrain_listing, load_track_config().command), 2, "mujoco", "cpu",
                         evaluation=True)
    assert prepared.terrain.clip_origin_w.tolist() == from_files.terrain.clip_origin_w.tolist() == [
        [0.0, 0.0, 0.0], [50.0, 0.0, 0.0]]
    assert prepared.terrain.info() == from_files.terrain.info()
    for field in dataclasses.fields(from_files.motion):
        mine, theirs = getattr(prepared.motion, field.name), getattr(from_files.motion, field.name)
        assert torch.equal(mine, theirs) if isinstance(theirs, torch.Tensor) else mine == theirs, field.name


def test_clips_prepared_for_another_rate_are_refused(terrain_listing):
    cfg = load_track_config()
    at_30_fps = dataclasses.replace(cfg.command, fps=30.0)
    clips = prepare_clips(terrain_listing, at_30_fps)
    with pytest.raises(ValueError, match=r"fps 30\.0 \(clips\) vs 50\.0 \(environment\)"):
        make_task(clips, 1, "mujoco", "cpu", cfg, evaluation=True)
