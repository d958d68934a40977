"""The Python blocks of README and of the guides run as written, with small inputs in place of their paths.

README's example runs on the real OMOMO clip of the shared data (skipped without it); the guides'
on generated clips. Each substitution must find its text: an edit that renames a path or an
argument fails here instead of silently running something else."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from otr_gym.reference import Reference
from retarget.inputs import readers
from retarget.inputs.demonstration import Demonstration

from clips import clip
from conftest import REPO_ROOT

README = REPO_ROOT / "README.md"
DOCS = REPO_ROOT / "docs"
#: The guides whose Python examples run here.
GUIDES = (DOCS / "retargeting.md", DOCS / "box.md", DOCS / "formats.md")


def python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


def test_readme_and_guides_have_python_examples():
    assert len(python_blocks(README)) >= 1
    assert all(python_blocks(guide) for guide in GUIDES)


def _first_frames(demo: Demonstration, frames: int) -> Demonstration:
    """The demonstration's first ``frames`` frames (objects and labels cut too)."""
    s = slice(0, frames)
    objects = [replace(o, pos_w=o.pos_w[s], quat_w=o.quat_w[s]) for o in demo.objects]
    return replace(demo, part_pos_w=demo.part_pos_w[s], part_quat_w=demo.part_quat_w[s], objects=objects,
                   annotations={k: v[s] for k, v in demo.annotations.items()})


def run_blocks(blocks: list[str], substitutions: dict[str, str], origin: Path) -> dict:
    """Run ``blocks`` in one namespace after the substitutions; every substitution must be used."""
    namespace: dict = {}
    used = set()
    for block in blocks:
        for old, new in substitutions.items():
            if old in block:
                block = block.replace(old, new)
                used.add(old)
        exec(compile(block, str(origin), "exec"), namespace)  # noqa: S102 - the documentation's own code
    unused = sorted(set(substitutions) - used)
    assert not unused, f"{origin.name} no longer contains {unused}: update this test's substitutions"
    return namespace


def test_readme_python_block_runs_on_the_real_omomo_clip(tmp_path, shared_data, walking_reference, monkeypatch):
    """The README's example as a user runs it: the OMOMO clip and its mesh passed explicitly, read by the
    real OMOMO reader; only the first 10 frames (1/3 s) are retargeted, to keep the test short."""
    refs = tmp_path / "refs"
    refs.mkdir()
    (refs / "walk.npz").write_bytes(Path(walking_reference).read_bytes())
    read, load_demonstration = [], readers.load_demonstration

    def first_frames_of_the_clip(path, object_mesh=None, **kwargs):
        read.append((Path(path), Path(object_mesh)))
        return _first_frames(load_demonstration(path, object_mesh, **kwargs), 10)

    monkeypatch.setattr("retarget.inputs.readers.load_demonstration", first_frames_of_the_clip)
    monkeypatch.chdir(tmp_path)
    substitutions = {
        'reference="walk.npz"': f'reference="{walking_reference}"',
        "num_envs=4096": "num_envs=2",
        'device="cuda"': 'device="cpu"',
        'reference="refs/"': f'reference="{refs}"',
        '"sub3_largebox_003.pt"': f'"{shared_data / "omomo" / "sub3_largebox_003.pt"}"',
        '"largebox.obj"': f'"{shared_data / "objects" / "largebox.obj"}"',
    }
    namespace = run_blocks(python_blocks(README), substitutions, README)
    try:
        obs = namespace["obs"]
        assert obs["policy"].shape == (2, 154) and obs["critic"].shape == (2, 286)  # README's comment, 2 envs
        assert np.isfinite(obs["policy"].cpu().numpy()).all()
        assert read == [(shared_data / "omomo" / "sub3_largebox_003.pt", shared_data / "objects" / "largebox.obj")]
        saved = Reference.load(tmp_path / "sub3_largebox_003.npz")
        assert saved.num_frames == 16 and saved.fps == 50.0  # 10 frames at 30 fps, solved at 50 fps
        assert [o.name for o in saved.objects] == ["largebox"]  # the box was solved with the robot
    finally:
        namespace["vec"].close()
        namespace["env"].close()


def test_guides_python_blocks_run(tmp_path, box_reference):
    """The guides' examples (object substitution, the box task, references) with small generated inputs."""
    box_demo_path = clip("box_carry", 150, 160).save(tmp_path / "short_box_demo.npz")
    substitutions = {
        '"box_carry_demo.npz"': f'"{box_demo_path}"',
        '"out/demo/box_carry.npz"': f'"{box_reference}"',
        '"out/omomo/sub3_largebox_003.npz"': f'"{box_reference}"',
        "num_envs=4096": "num_envs=2",
        'device="cuda"': 'device="cpu"',
        '"refs/clip.npz"': f'"{box_reference}"',
        '"refs/clip_from_10.npz"': f'"{tmp_path / "clip_from_10.npz"}"',
    }
    blocks = [block for guide in GUIDES for block in python_blocks(guide)]
    namespace = run_blocks(blocks, substitutions, DOCS)
    try:
        assert namespace["clip"].num_frames == namespace["ref"].num_frames - 10
        assert Reference.load(tmp_path / "clip_from_10.npz").num_frames == namespace["clip"].num_frames
    finally:
        namespace["vec"].close()
        namespace["env"].close()


def test_make_vec_with_the_readme_mode_builds_the_vector_env(walking_reference):
    import gymnasium

    import otr_gym  # noqa: F401 - registers the environments

    vec = gymnasium.make_vec("OTR-G1-Track-v0", num_envs=2, vectorization_mode="vector_entry_point",
                             device="cpu", reference=str(walking_reference))
    try:
        assert vec.num_envs == 2 and type(vec).__name__ == "TrackVecEnv"
    finally:
        vec.close()
    with pytest.raises(ValueError, match="Invalid vectorization mode: 'vector_entrypoint'"):
        gymnasium.make_vec("OTR-G1-Track-v0", num_envs=2, vectorization_mode="vector_entrypoint",
                           device="cpu", reference=str(walking_reference))
