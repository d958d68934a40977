"""``otr train`` reads its inputs once and hands them down (agents -> envs): each clip list is
parsed once, each clip file loaded and prepared once, each terrain mesh placed once and the
environment's config read once, however many layers (library, terrain, vector env, task) use
them. A tiny run on the CPU: a clip list with a terrain clip, plus a reference file beside it."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest
import torch
import trimesh

import envs.terrain
from agents.procedural import WalkSpec, walking_reference
from envs.config import DEFAULT_CONFIG
from otr_gym import cli
from otr_gym.reference import Reference

PLATFORM_TOP_M = 0.05


@pytest.fixture(scope="module", autouse=True)
def single_torch_thread():
    """One intra-op thread: PPO's small updates are ~10x slower with OpenMP threads waiting on a
    small shared CPU (see test_agents_training.py)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def library(tmp_path) -> dict[str, Path]:
    """clips.txt (a flat walk; the walk raised onto a 5 cm platform, ``terrain=platform.obj``)
    and a shorter walk given beside the list."""
    walk = walking_reference(WalkSpec(steps=4))
    paths = {"flat": walk.save(tmp_path / "flat_walk.npz"),
             "raised": walk.translated([0.0, 0.0, PLATFORM_TOP_M]).save(tmp_path / "platform_walk.npz"),
             "short": walking_reference(WalkSpec(steps=3)).save(tmp_path / "short_walk.npz"),
             "mesh": tmp_path / "platform.obj", "list": tmp_path / "clips.txt"}
    platform = trimesh.creation.box(extents=(4.0, 2.0, 0.15))
    platform.apply_translation((0.5, 0.0, PLATFORM_TOP_M - 0.075))
    platform.export(paths["mesh"])
    paths["list"].write_text(f"flat_walk.npz\nplatform_walk.npz  terrain={paths['mesh'].name}\n")
    return {name: path.resolve() for name, path in paths.items()}


@pytest.fixture
def reads(monkeypatch) -> Counter:
    """Counts by (what, absolute path): text files read (clip lists, YAML configs), references
    loaded, clips prepared (resampled to the policy rate) and terrain meshes placed."""
    counts: Counter = Counter()
    read_text, load, resampled = Path.read_text, Reference.load.__func__, Reference.resampled
    load_terrain = envs.terrain.load_terrain

    def counting_read_text(self, *args, **kwargs):
        counts["read", self.resolve()] += 1
        return read_text(self, *args, **kwargs)

    def counting_load(cls, path):
        counts["load", Path(path).resolve()] += 1
        return load(cls, path)

    def counting_resampled(self, fps):
        counts["prepare", Path(self.source).resolve()] += 1
        return resampled(self, fps)

    def counting_load_terrain(file, *args, **kwargs):
        counts["terrain", Path(file).resolve()] += 1
        return load_terrain(file, *args, **kwargs)

    monkeypatch.setattr(Path, "read_text", counting_read_text)
    monkeypatch.setattr(Reference, "load", classmethod(counting_load))
    monkeypatch.setattr(Reference, "resampled", counting_resampled)
    monkeypatch.setattr(envs.terrain, "load_terrain", counting_load_terrain)
    return counts


def _of(reads: Counter, what: str) -> dict[Path, int]:
    return {path: n for (kind, path), n in reads.items() if kind == what}


@pytest.mark.slow
def test_train_reads_each_clip_list_clip_mesh_and_the_env_config_once(library, reads, tmp_path):
    rc = cli.main(["train", "--reference", str(library["list"]), str(library["short"]), "--num-envs", "2",
                   "--device", "cpu", "--iterations", "1", "--save-interval", "1", "--log-dir", str(tmp_path / "runs"),
                   "--set", "num_steps_per_env=2"])
    assert rc == 0
    clips = {library[name]: 1 for name in ("flat", "raised", "short")}
    assert reads["read", library["list"]] == 1
    assert reads["read", DEFAULT_CONFIG.resolve()] == 1
    assert _of(reads, "load") == clips
    assert _of(reads, "prepare") == clips
    assert _of(reads, "terrain") == {library["mesh"]: 1}
