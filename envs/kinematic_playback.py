"""Kinematic playback of a box reference: the robot put on the reference at every physics step
(qpos interpolated between frames, qvel from the reference), only the objects simulated (MuJoCo on
the CPU, the OTR-G1-BoxTrack-v0 model: fitted hand boxes, grasp-fitted box, nominal mass and
friction, no randomisation; or, with ``draw_seed``, one draw of the training's object
randomisation: friction, mass, inertia). What a policy that tracks perfectly, squeezing no harder than the
reference's hands, does to the box, where the reference holds it (``HeldGrasp``: a box held
below its centre tips in the hands unless squeezed) and which robot collision geoms the reference
itself puts inside the simulated box (``GeomOverlap``: a torso or shoulder in there shoves the box
aside). ``play_draws`` plays one reference under several draws, building the task once.
``benchmarks/grasp_playback.py`` is its command line.

The robot must also be immovable *within* each step's contact solve: left as the unactuated G1,
its links fall and swing under gravity during the step, and a hand accelerating away from the box
faster than the contact's reference acceleration switches the contact off (MuJoCo's "satisfied"
state) although it is millimetres deep. ``kinematic_robot`` gives the robot's joints an armature
so large that neither gravity nor contact forces accelerate them: the contacts then act as
against a body driven on the reference, as a perfect tracker's stiff joints would.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np
import torch

from envs.box import make_box_task
from envs.config import load_box_config
from envs.mdp.objects import GeomOverlap, HeldGrasp, held_grasp, reference_overlaps
from envs.mdp.randomization import randomize_objects
from otr_gym.config import merge
from otr_gym.reference import Reference
from otr_gym.rotations import quat_apply_inverse, quat_error_angle


@dataclass
class Playback:
    reference: str
    frames: int  # frames played after the first
    clip_frames: int
    ended_at: int | None  # frame where the object passed the termination, None if carried to the end
    termination_m: float  # the box task's object termination (terminations.object_pos), which ends the playback
    pos_error_cm: list[float]  # per frame played, moving object 0
    ori_error_deg: list[float]
    grasp: HeldGrasp | None = None  # the reference's hold, None when it never holds a box
    #: robot collision geoms inside the simulated objects on the reference itself, deepest first
    overlaps: list[GeomOverlap] = field(default_factory=list)
    #: the object randomisation's draw (body -> [friction, mass kg, inertia scale]); None: nominal
    draw: dict[str, list[float]] | None = None

    def overlap_line(self) -> str:
        """The overlaps in one line: geom depth (frames), hands marked as the squeeze."""
        if not self.overlaps:
            return f"{Path(self.reference).name}: no robot collision geom inside the simulated objects"
        parts = [f"{o.geom} {1000 * o.deepest_m:.1f} mm ({o.frames} frames){' [hand]' if o.hand else ''}"
                 for o in self.overlaps]
        return f"{Path(self.reference).name}: inside the simulated objects on the reference: " + ", ".join(parts)

    def row(self) -> str:
        pos, ori = np.asarray(self.pos_error_cm), np.asarray(self.ori_error_deg)
        end = "–" if self.ended_at is None else f"frame {self.ended_at}"
        g = self.grasp
        hold = "– | – | – | –" if g is None else \
            f"{g.frames} | {g.hand_height:+.2f} | {g.hand_centre_height:+.2f} | " \
            f"{g.centre_height_m:.2f} m, {g.tilt_deg:.0f}°"
        return (f"| {Path(self.reference).name} | {self.frames} / {self.clip_frames - 1} | {pos.mean():.1f} / "
                f"{np.percentile(pos, 95):.1f} | {ori.mean():.1f} / {ori.max():.1f} | {end} | {hold} |")


#: Armature (kg, kg·m²) added to every robot degree of freedom in the playback: 10⁶ × a G1 link's
#: mass. 10³ gives the same picture (ours and the demo: the same frames carried; Holosoma's 78, not 84).
ROBOT_ARMATURE = 1.0e6


def kinematic_robot(model: mujoco.MjModel, robot_dofs: int) -> mujoco.MjModel:
    """``model`` with the first ``robot_dofs`` degrees of freedom (the G1's free base and joints)
    made immovable for the solver (in place; returned for chaining)."""
    model.dof_armature[:robot_dofs] += ROBOT_ARMATURE
    return model


def _robot_state(motion, qpos_all: torch.Tensor, f: float) -> tuple[np.ndarray, np.ndarray]:
    """Reference qpos (root xyz, wxyz, joints) and qvel (root linear world, angular body, joints)
    at fractional frame f, linearly interpolated (quaternion renormalised)."""
    f0 = int(np.floor(f))
    f1, a = min(f0 + 1, len(qpos_all) - 1), f - f0
    lerp = lambda x: (1 - a) * x[f0] + a * x[f1]  # noqa: E731
    qpos = lerp(qpos_all)
    qpos[3:7] /= qpos[3:7].norm()
    ang_b = quat_apply_inverse(qpos[3:7].float(), lerp(motion.root_ang_vel_w))
    qvel = torch.cat([lerp(motion.root_lin_vel_w), ang_b, lerp(motion.joint_vel)])
    return qpos.numpy(), qvel.double().numpy()


def play(reference: str | Path, object_meshes: dict[str, str] | None = None,
         env_overrides: dict | None = None, draw_seed: int | None = None) -> Playback:
    """Play one reference; ``object_meshes`` (name -> mesh file) for the reference's objects that
    embed no mesh, names the reference does not have are ignored; ``env_overrides`` change the
    box config (nested keys of configs/env/box.yaml, e.g. {"objects": {"grasp_fit": False}});
    ``draw_seed``: the moving objects' friction, mass and inertia drawn as in training
    (``objects.randomization``, ``randomize_objects``) from this seed, instead of nominal."""
    return play_draws(reference, [draw_seed], object_meshes, env_overrides)[0]


def play_draws(reference: str | Path, draw_seeds: Sequence[int | None], object_meshes: dict[str, str] | None = None,
               env_overrides: dict | None = None) -> list[Playback]:
    """``play`` once per entry of ``draw_seeds`` (None: nominal), the task, the reference's hold
    and overlaps and the robot's path built once for all of them."""
    ref = Reference.load(reference)
    names = {t.name for t in ref.objects}
    meshes = {"objects": {"overrides": {n: {"mesh": m} for n, m in (object_meshes or {}).items() if n in names}}}
    cfg = load_box_config(None, merge(env_overrides or {}, meshes))
    task = make_box_task(reference, 1, "mujoco", "cpu", cfg=cfg, evaluation=True, autoreset=False)
    motion, objects = task.motion, task.objects
    if motion.num_clips != 1:
        raise ValueError(f"{reference}: one clip at a time ({motion.num_clips} given)")
    grasp = held_grasp(ref, task.scene, task.backend.model, cfg.objects)
    overlaps = reference_overlaps(ref, task.scene, task.backend.model, cfg.objects)
    last = int(motion.clip_length[0]) - 1
    nq, nv = 7 + motion.joint_pos.shape[1], 6 + motion.joint_pos.shape[1]
    decimation = cfg.sim.decimation
    qpos_all = motion.qpos(torch.arange(last + 1)).double()
    # the robot's state at the start and after every physics substep: the same for every draw
    path = [_robot_state(motion, qpos_all, f / decimation) for f in range(last * decimation + 1)]
    start = torch.cat([objects.pos_w[0, 0], objects.quat_w[0, 0]]).numpy()
    termination = float(cfg.terminations["object_pos"].params["threshold_m"])
    moving = [o.body for o in task.scene.moving]
    # the world's own model: the draws below change its objects (absolutely, not cumulatively)
    model = kinematic_robot(task.backend.world_model(0), nv)  # the task is ours alone: changed in place
    nominal = model.geom_friction.copy(), model.body_mass.copy(), model.body_inertia.copy()
    out = []
    for seed in draw_seeds:
        draw = None
        if seed is None:
            model.geom_friction[:], model.body_mass[:], model.body_inertia[:] = nominal
        else:
            drawn = randomize_objects(task.backend, moving, [o.mass_kg for o in task.scene.moving],
                                      cfg.objects.randomization, torch.Generator().manual_seed(seed))
            draw = {body: [float(x) for x in values[0]] for body, values in drawn.items()}
        data = mujoco.MjData(model)
        data.qpos[:nq], data.qvel[:nv] = path[0]
        data.qpos[nq:nq + 7] = start
        mujoco.mj_forward(model, data)
        pos_err, ori_err, ended = [], [], None
        for f in range(1, last + 1):
            for k in range(decimation):
                data.qpos[:nq], data.qvel[:nv] = path[(f - 1) * decimation + k + 1]
                mujoco.mj_step(model, data)
            box = torch.from_numpy(data.qpos[nq:nq + 7].copy()).float()
            err = float(torch.linalg.norm(box[:3] - objects.pos_w[f, 0]))
            pos_err.append(100 * err)
            ori_err.append(float(torch.rad2deg(quat_error_angle(objects.quat_w[f, 0], box[3:] / box[3:].norm()))))
            if err > termination:
                ended = f
                break
        out.append(Playback(str(reference), len(pos_err), last + 1, ended, termination, pos_err, ori_err, grasp,
                            overlaps, draw))
    return out


def draws_summary(runs: list[Playback]) -> dict:
    """The spread of playbacks of one reference under object draws: runs carried to the clip's end,
    each run's mean box error (cm; a run that loses the box averages over the frames it played),
    their mean, sd, min and max, the mean p95 and the mean orientation error (deg)."""
    means = np.array([np.mean(r.pos_error_cm) for r in runs])
    return {"runs": len(runs), "carried": sum(r.ended_at is None for r in runs),
            "error_cm_mean": float(means.mean()), "error_cm_sd": float(means.std()),
            "error_cm_min": float(means.min()), "error_cm_max": float(means.max()),
            "error_p95_cm": float(np.mean([np.percentile(r.pos_error_cm, 95) for r in runs])),
            "orientation_deg": float(np.mean([np.mean(r.ori_error_deg) for r in runs]))}


def draws_row(name: str, summary: dict) -> str:
    """One markdown row of ``draws_summary`` (see ``DRAWS_HEADER``)."""
    s = summary
    return (f"| {name} | {s['carried']} / {s['runs']} | {s['error_cm_mean']:.1f} ± {s['error_cm_sd']:.1f} "
            f"({s['error_cm_min']:.1f}–{s['error_cm_max']:.1f}) | {s['error_p95_cm']:.1f} | "
            f"{s['orientation_deg']:.1f} |")


DRAWS_HEADER = ("| reference | runs carried to the end | box error cm, mean of a run: mean ± sd (min–max) "
                "| p95 cm (mean) | orientation deg (mean) |\n|---|---|---|---|---|")

