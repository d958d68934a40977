"""OTR-Gym: human motion capture → Unitree G1 references → whole-body tracking policies.

Importing the package registers the Gymnasium environments. Entry points are strings, so
nothing heavy (mujoco, mujoco_warp, torch) is imported here.

Offscreen rendering: MuJoCo picks its OpenGL backend when it is first imported, so the
default is set here, before any of our modules can import it — EGL (GPU or Mesa) on a Linux
machine without a display, unless the user chose one (``MUJOCO_GL=osmesa`` / ``glfw``).
"""

import os
import sys

import gymnasium

if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")

if "OTR-G1-Track-v0" not in gymnasium.registry:
    gymnasium.register(
        id="OTR-G1-Track-v0",
        entry_point="envs.tracking:TrackEnv",
        vector_entry_point="envs.tracking:TrackVecEnv",
    )
if "OTR-G1-BoxTrack-v0" not in gymnasium.registry:
    gymnasium.register(
        id="OTR-G1-BoxTrack-v0",
        entry_point="envs.box:BoxTrackEnv",
        vector_entry_point="envs.box:BoxTrackVecEnv",
    )
