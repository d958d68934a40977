"""Gymnasium environments of OTR-Gym: ``tracking`` (OTR-G1-Track-v0) on the physics backends of
``envs.backends``, with the MDP terms of ``envs.mdp`` configured by ``configs/env/*.yaml``."""
