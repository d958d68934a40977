"""Offscreen pictures: the G1 and rigid meshes (objects, human parts) replayed kinematically.

One renderer for everything we show: a scene of the G1 (optional) plus any number of rigid
mesh tracks (``RigidTrack``: mesh in its own frame + world poses per frame), built once as
MuJoCo mocap bodies and posed frame by frame. References give the G1 and their objects;
demonstrations give one track per human part and per object (``retarget`` builds those).
Uses MuJoCo's offscreen renderer (``MUJOCO_GL=egl`` by default, set by ``otr_gym``;
``osmesa`` also works).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from otr_gym.reference import Reference
from otr_gym.robot import G1_MJCF
from otr_gym.scene import GROUND_XML

HUMAN_RGBA = (0.85, 0.72, 0.55, 1.0)
OBJECT_RGBA = (0.8, 0.55, 0.3, 1.0)


@dataclass(frozen=True)
class RigidTrack:
    """A rigid mesh (object frame, m) and its world poses over time (T, 3) / (T, 4) wxyz."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    pos_w: np.ndarray
    quat_w: np.ndarray
    rgba: tuple[float, float, float, float] = OBJECT_RGBA


@dataclass(frozen=True)
class Camera:
    """Free camera following a target point (m, world)."""

    azimuth_deg: float = 120.0
    elevation_deg: float = -12.0
    distance_m: float = 3.2
    lookat_height_m: float = 0.7


def reference_tracks(ref: Reference) -> list[RigidTrack]:
    """The reference's objects as tracks (embedded meshes; a 30 cm cube when none is stored)."""
    import trimesh

    cube = trimesh.creation.box((0.3, 0.3, 0.3))
    return [RigidTrack(o.name, o.mesh_vertices if o.mesh_vertices is not None else cube.vertices,
                       o.mesh_faces if o.mesh_faces is not None else cube.faces, o.pos_w, o.quat_w)
            for o in ref.objects]


class SceneRenderer:
    """Renders frames of a G1 trajectory and rigid tracks with one compiled model."""

    def __init__(self, tracks: list[RigidTrack], robot: bool = True, width: int = 320, height: int = 400,
                 camera: Camera = Camera()):
        spec = mujoco.MjSpec.from_file(str(G1_MJCF)) if robot else mujoco.MjSpec()
        ground = mujoco.MjSpec.from_file(str(GROUND_XML))
        spec.attach(ground, prefix="ground/", frame=spec.worldbody.add_frame())
        spec.visual.global_.offwidth, spec.visual.global_.offheight = max(width, 640), max(height, 480)
        for k, track in enumerate(tracks):
            body = spec.worldbody.add_body(name=f"track{k}_{track.name}", mocap=True)
            spec.add_mesh(name=f"track{k}_mesh", uservert=np.asarray(track.vertices, np.float64).ravel().tolist(),
                          userface=np.asarray(track.faces, np.int32).ravel().tolist())
            body.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"track{k}_mesh", rgba=list(track.rgba),
                          contype=0, conaffinity=0)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.tracks = tracks
        self.robot = robot
        self.camera = camera
        self.size = (height, width)

    def render(self, frames, robot_qpos: np.ndarray | None = None,
               follow: np.ndarray | None = None) -> list[np.ndarray]:
        """RGB images (H, W, 3) at ``frames``; ``robot_qpos`` (T, 36) poses the G1; the camera
        looks at ``follow`` (T, 3) when given, else at the robot root or the first track."""
        cam = mujoco.MjvCamera()
        cam.azimuth, cam.elevation, cam.distance = (self.camera.azimuth_deg, self.camera.elevation_deg,
                                                     self.camera.distance_m)
        images = []
        with mujoco.Renderer(self.model, *self.size) as renderer:
            for t in frames:
                if self.robot and robot_qpos is not None:
                    self.data.qpos[:36] = robot_qpos[t]
                for k, track in enumerate(self.tracks):
                    self.data.mocap_pos[k] = track.pos_w[t]
                    self.data.mocap_quat[k] = track.quat_w[t]
                mujoco.mj_forward(self.model, self.data)
                target = (follow[t] if follow is not None else
                          robot_qpos[t, :3] if robot_qpos is not None else self.tracks[0].pos_w[t])
                cam.lookat[:] = [target[0], target[1], self.camera.lookat_height_m]
                renderer.update_scene(self.data, camera=cam)
                images.append(renderer.render().copy())
        return images


def render_reference(ref: Reference, frames, **kw) -> list[np.ndarray]:
    return SceneRenderer(reference_tracks(ref), robot=True, **kw).render(frames, robot_qpos=ref.qpos())


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write an RGB image atomically (temporary file + rename)."""
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    iio.imwrite(tmp, image, extension=".png")
    os.replace(tmp, path)
    return path


def strip(images: list[np.ndarray], gap_px: int = 2) -> np.ndarray:
    """Images side by side with white gaps."""
    gap = np.full((images[0].shape[0], gap_px, 3), 255, np.uint8)
    return np.concatenate([x for img in images for x in (img, gap)][:-1], axis=1)


def grid(rows: list[list[np.ndarray]], gap_px: int = 2) -> np.ndarray:
    """Rows of images (each row a strip) stacked vertically with white gaps."""
    strips = [strip(r, gap_px) for r in rows]
    gap = np.full((gap_px, strips[0].shape[1], 3), 255, np.uint8)
    return np.concatenate([x for s in strips for x in (s, gap)][:-1], axis=0)


def save_reference_strip(ref: Reference, path: str | Path, count: int = 6, **kw) -> Path:
    frames = np.linspace(0, ref.num_frames - 1, count).round().astype(int)
    return save_png(strip(render_reference(ref, frames, **kw)), path)
