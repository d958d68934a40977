"""Short procedural demonstrations for the retargeting tests (generated, never downloaded)."""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

from retarget.inputs.demonstration import Demonstration
from retarget.inputs.synthetic import generate


@lru_cache(maxsize=4)
def _full(kind: str) -> Demonstration:
    return generate(kind, seed=0, fps=30.0)


def clip(kind: str, start: int, stop: int) -> Demonstration:
    """Frames [start, stop) of the seed-0 synthetic ``kind`` at 30 fps (objects and labels sliced too)."""
    demo = _full(kind)
    s = slice(start, stop)
    objects = [replace(o, pos_w=o.pos_w[s], quat_w=o.quat_w[s]) for o in demo.objects]
    annotations = {k: v[s] for k, v in demo.annotations.items()}
    return replace(demo, name=f"{demo.name}[{start}:{stop}]", part_pos_w=demo.part_pos_w[s],
                   part_quat_w=demo.part_quat_w[s], objects=objects, annotations=annotations)


def tpose(source: dict, frames: int = 10) -> Demonstration:
    """The human standing still in the T-pose for ``frames`` frames at 30 fps, soles on z = 0,
    facing +x, with the given ``source`` record."""
    import numpy as np

    from retarget.inputs.human import PART_NAMES, PART_PARENTS, HumanModel, human_tpose

    model = HumanModel()
    pos, quat = human_tpose(model)
    return Demonstration(name="tpose", fps=30.0, part_names=PART_NAMES, part_parents=PART_PARENTS,
                         part_pos_w=np.tile(pos, (frames, 1, 1)), part_quat_w=np.tile(quat, (frames, 1, 1)),
                         surface=model.surface, shape=model.shape, stature_m=model.stature_m, source=source)
