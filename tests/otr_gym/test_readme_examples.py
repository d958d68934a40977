"""README's Python blocks run as written, with small generated inputs in place of its paths.

Each substitution must find its text: a README edit that renames a path or an argument fails
here instead of silently running something else."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from clips import clip
from conftest import REPO_ROOT

README = REPO_ROOT / "README.md"


def python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_has_python_examples():
    assert len(python_blocks()) >= 1


def test_readme_python_blocks_run(tmp_path, walking_reference, box_reference, monkeypatch):
    refs = tmp_path / "refs"
    refs.mkdir()
    (refs / "walk.npz").write_bytes(Path(walking_reference).read_bytes())
    demo_path = clip("walk", 40, 50).save(tmp_path / "short_walk_demo.npz")
    box_demo_path = clip("box_carry", 150, 160).save(tmp_path / "short_box_demo.npz")
    substitutions = {
        'reference="walk.npz"': f'reference="{walking_reference}"',
        "num_envs=4096": "num_envs=2",
        'device="cuda"': 'device="cpu"',
        'reference="refs/"': f'reference="{refs}"',
        '"sub3_largebox_003.pt"': f'"{demo_path}"',
        '"box_carry_demo.npz"': f'"{box_demo_path}"',
        '"out/demo/box_carry.npz"': f'"{box_reference}"',
        '"out/omomo/sub3_largebox_003.npz"': f'"{box_reference}"',
    }
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    used = set()
    for block in python_blocks():
        for old, new in substitutions.items():
            if old in block:
                block = block.replace(old, new)
                used.add(old)
        exec(compile(block, str(README), "exec"), namespace)  # noqa: S102 - the README's own code
    unused = sorted(set(substitutions) - used)
    assert not unused, f"README no longer contains {unused}: update this test's substitutions"
    obs = namespace["obs"]
    assert obs["policy"].shape == (2, 154) and obs["critic"].shape == (2, 286)  # README's comment, 2 envs
    assert np.isfinite(obs["policy"].cpu().numpy()).all()
    from otr_gym.reference import Reference

    saved = Reference.load(tmp_path / "sub3_largebox_003.npz")
    assert saved.num_frames == 16 and saved.fps == 50.0  # 10 frames at 30 fps, solved at 50 fps
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
