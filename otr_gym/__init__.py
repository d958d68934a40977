"""OTR-Gym: human motion capture → Unitree G1 references → whole-body tracking policies.

Importing the package registers the Gymnasium environments. Entry points are strings, so
nothing heavy (mujoco, mujoco_warp, torch) is imported here.
"""

import gymnasium

if "OTR-G1-Track-v0" not in gymnasium.registry:
    gymnasium.register(
        id="OTR-G1-Track-v0",
        entry_point="envs.tracking:TrackEnv",
        vector_entry_point="envs.tracking:TrackVecEnv",
    )
