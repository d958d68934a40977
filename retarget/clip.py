"""One demonstration in, one G1 ``Reference`` out: the whole method on a clip.

``retarget_demonstration(demo, cfg)`` resamples the demonstration, builds the problem (probes,
distance grids, OT correspondences), solves the SQP frame by frame (a second time where
``balance`` or ``flight`` asks, ``retarget.solver.balance``) and assembles the reference with its
objects, contact annotations and metadata.

Output rate (our choice): the demonstration is resampled to ``cfg.fps`` (default 50, what the
Holosoma / BeyondMimic trackers expect) *before* solving, so every stored frame is a solved,
constraint-checked frame (interpolating a solution would not keep its contacts).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from retarget.config import RetargetConfig


def retarget_demonstration(demo, cfg: RetargetConfig = RetargetConfig(), progress=None):
    """Retarget one Demonstration to a G1 ``Reference`` (see the module doc for the rate).

    ``progress(t)`` is called after each solved frame (of both passes when ``cfg.balance`` or
    ``cfg.flight`` solves the clip twice). The reference carries the free and fixed
    objects' tracks (with meshes), per-link contact annotations against every channel, and
    metadata (mode, scale, weights, source, solver statistics). Wall-clock times are not in
    it (``retarget_timed`` returns them), so the same clip always gives the same file.
    """
    return retarget_timed(demo, cfg, progress)[0]

@dataclass(frozen=True)
class Timing:
    """Where one clip's time went (s), and the solve time per output frame (ms)."""

    setup_s: float
    solve_s: float
    frames: int

    @property
    def ms_per_frame(self) -> float:
        return 1000.0 * self.solve_s / max(self.frames, 1)

def problem_from_config(demo, cfg: RetargetConfig):
    """``retarget.solver.problem.build_problem`` of ``demo`` (at its own fps) with every setting of
    ``cfg``, the person's centre of mass as a target where ``cfg.balance`` asks for it."""
    from retarget.solver.balance import person_com_problem
    from retarget.solver.problem import build_problem

    problem = build_problem(demo, cfg.mode, geometry=cfg.geometry, interaction=cfg.interaction, style=cfg.style,
                            solver=cfg.solver, guard_spacing_m=cfg.guard_spacing_m,
                            max_probes_per_link=cfg.max_probes_per_link, seed=cfg.seed, stance=cfg.stance,
                            links_together=cfg.links_together)
    return person_com_problem(problem, demo, cfg.mode, cfg.balance)

def retarget_timed(demo, cfg: RetargetConfig = RetargetConfig(), progress=None):
    """``retarget_demonstration`` that also returns its ``Timing``."""
    from otr_gym.reference import ContactAnnotations, ObjectTrack, Reference
    from otr_gym.robot import BODY_NAMES
    from otr_gym.rotations import (
        angular_velocity_from_quats,
        linear_velocity_from_positions,
        matrix_to_quat,
    )
    from retarget.geometry.kernel_warmup import finish_warmup
    from retarget.solver.balance import balance_problem
    from retarget.solver.problem import mode_scale, resample_demonstration
    from retarget.solver.sqp import solve_sequence

    start = time.perf_counter()
    if cfg.fps is not None:
        demo = resample_demonstration(demo, cfg.fps)
    problem = problem_from_config(demo, cfg)
    finish_warmup()  # the kernels a first run's command line began compiling beside the grids
    built = time.perf_counter()
    sol = solve_sequence(problem, progress)
    # solved again with the COM smoothed (retarget.solver.balance) and, with cfg.flight, its
    # flights thrown (retarget.solver.flight)
    second = balance_problem(problem, sol, cfg.balance, cfg.flight)
    passes = {"passes": 1}
    if second is not None:
        problem, stats = second
        sol = solve_sequence(problem, progress)
        passes = {"passes": 2, **stats}
    solved = time.perf_counter()

    dt = 1.0 / demo.fps
    meshes = {o.name: o for o in demo.objects}
    objects = []
    for track in problem.channels[1:]:
        free = [i for i, o in enumerate(problem.objects) if o.name == track.name]
        pos = sol.obj_pos[:, free[0]] if free else track.pos_w
        quat = matrix_to_quat(sol.obj_rot[:, free[0]] if free else track.rot_w)
        src = meshes[track.name]
        objects.append(ObjectTrack(track.name, pos, quat, linear_velocity_from_positions(pos, dt),
                                   angular_velocity_from_quats(quat, dt), src.vertices, src.faces))
    contacts = ContactAnnotations(BODY_NAMES, tuple(t.name for t in problem.channels), sol.contacts, sol.witness_c)
    iterations = np.array([s.iterations for s in sol.stats])
    rows = np.concatenate([np.asarray(s.qp_rows) for s in sol.stats if s.qp_rows] or [np.zeros(1)])
    metadata = {
        "generator": "otr-gym retarget (OTRetarget)",
        "mode": cfg.mode, "scale": mode_scale(demo, cfg.mode), "fps": demo.fps,
        "source": {"name": demo.name, **{k: v for k, v in demo.source.items() if _jsonable(v)}},
        "config": dataclasses.asdict(cfg),
        "free_objects": [o.name for o in problem.objects],
        "solver": {
            "frames": len(iterations), "iterations_mean": float(iterations.mean()),
            "iterations_max": int(iterations.max()), "rejected_steps": int(sum(s.rejected for s in sol.stats)),
            "qp_rows_mean": float(rows.mean()), "qp_rows_max": int(rows.max()),
            "qp_variables": problem.num_variables, "qp_failures": sol.qp_failures,
            "min_distance_m": float(min(s.min_distance_m for s in sol.stats)),
            "min_self_distance_m": float(min(s.min_self_distance_m for s in sol.stats)),
        },
        "passes": passes,
    }
    reference = Reference.from_qpos(sol.qpos, demo.fps, objects=objects, contacts=contacts, metadata=metadata)
    if cfg.trajectory.enabled:  # the paths repaired where they jump (retarget.solver.trajectory)
        from retarget.solver.trajectory import smooth_trajectory

        reference, report = smooth_trajectory(reference, cfg.trajectory, problem)
        reference.metadata["trajectory"] = {"flagged": report.flagged, "windows": len(report.windows),
                                            "unsolved_windows": report.unsolved,
                                            "moved_m": report.moved_m}
        solved = time.perf_counter()
    if cfg.grasp.enabled:  # two-hand holds of a box made a squeeze the G1 can do (retarget.solver.grasp)
        from retarget.solver.grasp import grasp_boxes

        reference, _ = grasp_boxes(reference, cfg.grasp)
        solved = time.perf_counter()
    return reference, Timing(built - start, solved - built, len(iterations))

def _jsonable(v) -> bool:
    return isinstance(v, (str, int, float, bool)) or v is None
