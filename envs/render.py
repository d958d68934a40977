"""Offscreen frames of the robot with a translucent ghost of the reference pose.

Uses ``mujoco.Renderer`` on the scene *with* visual meshes (the simulation model has none),
plus the box task's objects (their given meshes; collision geoms hidden) and the terrain (its
collision geometry, as simulated).
Headless machines need an offscreen OpenGL: set ``MUJOCO_GL=egl`` (GPU/EGL) or
``MUJOCO_GL=osmesa`` (software) before anything imports mujoco.
"""

from __future__ import annotations

import os

import mujoco
import numpy as np

from otr_gym import robot
from otr_gym.scene import SceneSpec, build_scene

GHOST_RGBA = (0.35, 0.75, 1.0, 0.35)


class TrackingRenderer:
    """Renders G1 configurations (qpos [xyz, wxyz, 29 joints], then 7 per moving object when
    ``objects`` (``envs.objects.SceneObjects``) are given) from a camera following the pelvis,
    on the ``terrain`` (``envs.terrain.SceneTerrain``) when given.
    The ghost shows the robot and the moving objects (static ones are drawn once)."""

    def __init__(self, width: int = 640, height: int = 480, distance_m: float = 3.0, azimuth_deg: float = 135.0,
                 elevation_deg: float = -15.0, objects=None, condim: int = 3, terrain=None):
        spec = build_scene(SceneSpec(visual=True)).spec
        if objects is not None:
            objects.add_to(spec, visual=True, condim=condim)
        if terrain is not None:
            terrain.add_to(spec)
        self.model = spec.compile()
        self.model.vis.global_.offwidth = max(self.model.vis.global_.offwidth, width)
        self.model.vis.global_.offheight = max(self.model.vis.global_.offheight, height)
        try:
            self._renderer = mujoco.Renderer(self.model, height=height, width=width)
        except Exception as exc:  # the GL backend fails with several exception types
            raise RuntimeError(
                f"offscreen rendering is unavailable (MUJOCO_GL={os.environ.get('MUJOCO_GL', '<unset>')!r}: {exc}); "
                "set MUJOCO_GL=egl or MUJOCO_GL=osmesa before importing mujoco") from exc
        self._robot = mujoco.MjData(self.model)
        self._ghost = mujoco.MjData(self.model)
        self._option = mujoco.MjvOption()
        self._perturb = mujoco.MjvPerturb()
        self._camera = mujoco.MjvCamera()
        self._camera.distance, self._camera.azimuth, self._camera.elevation = distance_m, azimuth_deg, elevation_deg
        self._pelvis = self.model.body(robot.ROOT_BODY).id

    def render(self, qpos: np.ndarray, ghost_qpos: np.ndarray | None = None) -> np.ndarray:
        """(height, width, 3) uint8 frame of ``qpos``, with ``ghost_qpos`` drawn translucent."""
        self._pose(self._robot, qpos)
        self._camera.lookat[:] = self._robot.xpos[self._pelvis]
        self._renderer.update_scene(self._robot, camera=self._camera, scene_option=self._option)
        if ghost_qpos is not None:
            scene = self._renderer.scene
            first = scene.ngeom
            self._pose(self._ghost, ghost_qpos)
            mujoco.mjv_addGeoms(self.model, self._ghost, self._option, self._perturb,
                                mujoco.mjtCatBit.mjCAT_DYNAMIC, scene)
            for i in range(first, scene.ngeom):
                scene.geoms[i].rgba[:] = GHOST_RGBA
        return self._renderer.render()

    def close(self) -> None:
        self._renderer.close()

    def _pose(self, data: mujoco.MjData, qpos: np.ndarray) -> None:
        data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, data)
        mujoco.mj_comPos(self.model, data)  # the MJCF's light tracks the com
        mujoco.mj_camlight(self.model, data)
