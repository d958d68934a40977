"""Offscreen pictures of references: the G1 (and its objects) replayed kinematically.

Uses MuJoCo's offscreen renderer (``MUJOCO_GL=egl`` on a GPU or Mesa, ``osmesa`` otherwise;
EGL is the default when nothing is set).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402

from otr_gym.reference import Reference  # noqa: E402
from otr_gym.scene import ObjectSpec, SceneSpec, build_scene  # noqa: E402


def reference_scene(ref: Reference) -> mujoco.MjModel:
    """G1 + ground + the reference's objects (embedded meshes, else a 30 cm cube)."""
    objects = tuple(
        ObjectSpec(o.name, vertices=o.mesh_vertices, faces=o.mesh_faces) if o.mesh_vertices is not None
        else ObjectSpec(o.name, box_half_extents=(0.15, 0.15, 0.15))
        for o in ref.objects)
    return build_scene(SceneSpec(objects=objects)).model


def render_frames(ref: Reference, frames, width: int = 320, height: int = 400,
                  azimuth_deg: float = 120.0, distance_m: float = 3.0) -> list[np.ndarray]:
    """RGB images (H, W, 3) of the reference at the given frame indices; camera follows the pelvis."""
    model = reference_scene(ref)
    data = mujoco.MjData(model)
    qpos = ref.qpos()
    cam = mujoco.MjvCamera()
    cam.azimuth, cam.elevation, cam.distance = azimuth_deg, -12.0, distance_m
    images = []
    with mujoco.Renderer(model, height, width) as renderer:
        for t in frames:
            data.qpos[:36] = qpos[t]
            for i, o in enumerate(ref.objects):
                data.qpos[36 + 7 * i: 36 + 7 * i + 7] = np.concatenate([o.pos_w[t], o.quat_w[t]])
            mujoco.mj_forward(model, data)
            cam.lookat[:] = [qpos[t, 0], qpos[t, 1], 0.7]
            renderer.update_scene(data, camera=cam)
            images.append(renderer.render().copy())
    return images


def save_strip(images: list[np.ndarray], path: str | Path) -> Path:
    """Concatenate images left to right (2 px white gaps) and write a PNG atomically."""
    import imageio.v3 as iio

    gap = np.full((images[0].shape[0], 2, 3), 255, np.uint8)
    strip = np.concatenate([x for img in images for x in (img, gap)][:-1], axis=1)
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    iio.imwrite(tmp, strip, extension=".png")
    os.replace(tmp, path)
    return path


def save_reference_strip(ref: Reference, path: str | Path, count: int = 6, **kw) -> Path:
    frames = np.linspace(0, ref.num_frames - 1, count).round().astype(int)
    return save_strip(render_frames(ref, frames, **kw), path)
