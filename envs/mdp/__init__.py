"""The tracking MDP as plain batched torch functions and small stateful pieces:

- ``motion``: reference clips on the device; ``commands``: per-env clip/frame and start sampling;
- ``state``: the per-step snapshot (``TrackingState``) every term reads;
- ``observations``, ``rewards``, ``terminations``: term functions named in the config;
- ``randomization``: domain randomisation; ``metrics``: tracking errors for evaluation.
"""
