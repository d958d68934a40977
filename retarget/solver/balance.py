"""The balance pass: a second solve that takes the per-frame solve's jitter out of the G1's
centre of mass.

Solved frame by frame, the G1's pelvis moves in small steps where the person's moves smoothly:
the stance rows hold it, the 3-iteration budget and the base step bound release it, and it
catches up a few millimetres at once (OMOMO ``sub3_largebox_003`` at 50 fps: the pelvis's
horizontal acceleration has a median of 10.8 m/s² against the person's 0.86; the COM's, after
the 6 Hz low-pass that ``otr verify`` applies, 2.2 m/s² against the person's body centroid's
0.6). Inverse dynamics turns that into forces the feet cannot supply: of the 292 frames with a
foot down that ``otr verify`` finds unsupported (over 20 % of the weight) on three default
references (box carry, AMASS jog, Bandai walk), the cart-table ZMP of the COM lies outside the
sole points' support polygon on 289 (docs/results/feasibility.md, *The balance pass*).

The pass (``balance_problem``, run by ``retarget.clip.retarget_timed`` after the first solve):

1. **Target**: the first solution's COM, its horizontal path low-passed (zero-phase Butterworth
   at ``cutoff_hz``, ``retarget.geometry.dynamics.lowpass``, the filter ``otr verify`` uses;
   with ``vertical`` its height too, else the height is not held). With
   ``flight.enabled`` its flights are then thrown (``retarget.solver.flight.ballistic_com``
   anchored on the smoothed path).
2. **Pass 2**: every style position target but the legs' moves by the correction c* − c (so the
   warm start and the pelvis step bound follow the smoothed body, while the feet stay where the
   person put them: the body moves over its feet), and the cost gains
   ``com_weight``·‖com(q) − c*_t‖² on the smoothed axes, as in the ballistic pass. Contacts,
   stance, collision and object rows are those of the first solve: the pass changes where the body sits over the
   feet, not what touches what.

``person_com_problem`` (``balance.person_com_weight``, off by default; on in
``configs/retarget/executable.yaml``) is the single-solve alternative: the first solve holds the
G1's horizontal COM on the person's, moved by the G1's own offset from it.

Frames: world, z up; COM in metres.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from otr_gym import robot
from retarget.geometry.centre_of_mass import com_path
from retarget.geometry.dynamics import lowpass
from retarget.solver.flight import FlightConfig, ballistic_com, supported_frames

if TYPE_CHECKING:
    from retarget.solver.problem import Problem
    from retarget.solver.sqp import Solution


#: The legs' links (``robot.BODY_NAMES`` indices: hips, knees, ankles), whose style targets the
#: balance pass leaves where they are.
LEG_LINKS = np.array([i for i, name in enumerate(robot.BODY_NAMES) if name.startswith(("left_", "right_"))
                      and name.split("_")[1] in ("hip", "knee", "ankle")])


@dataclass(frozen=True)
class BalanceConfig:
    """The balance pass (ours; the paper solves each frame once)."""

    #: Solve every clip a second time with its COM smoothed. Measured on the six shared clips
    #: (docs/results/feasibility.md, *The balance pass*): frames with over 20 % of the weight
    #: unsupported 678 → 410, the flagged share lower on all six, at twice the solve time. Off
    #: by default: the second solve also moves contacts the tests hold (a box placed on a table
    #: in a clip cut mid-carry: hand contact recall 0.5; a synthetic walk's stance foot more
    #: than 1.5 mm off the floor; the OMOMO box 0.35 mm into the floor, over ε_col).
    enabled: bool = False
    #: Cut-off of the COM's low-pass (Hz). Tried 3, 4 and 6 on the box carry and the Bandai
    #: walk: 4 left the fewest flagged frames (3 gave more joint-acceleration and limb-jump frames).
    cutoff_hz: float = 4.0
    #: Weight of ‖com(q) − c*‖² in pass 2 (per m²), as the ballistic pass's.
    com_weight: float = 1.0e4
    #: Smooth the COM's height too. Off: only its horizontal path (the part the cart-table ZMP
    #: sees) is smoothed and held, the height is left free to the contacts. Measured on the
    #: five shared clips: on, the box carry's unsupported frames fell further (55 → 29 against
    #: 55 → 40) but the wooden chair's pass 2 came apart (limb jumps 20 → 68, object J 83 → 53 %).
    vertical: bool = False
    #: Weight (per m², x and y) of the person's centre of mass as the G1's horizontal COM target
    #: in the first solve (``person_com_problem``); 0 switches it off. The person balanced
    #: their motion over their feet and the G1's feet stand where theirs did, so the person's
    #: smooth COM path is one the G1's contacts can carry, with no second solve. 1e4 in
    #: ``configs/retarget/executable.yaml`` (docs/results/feasibility.md, *Refused steps and the
    #: person's centre of mass*); off by default: on a synthetic clip that puts a box down on a
    #: table the hands leave the box (contact on 48 % of the frames), at 1e3-1e4 even with the
    #: G1's own low-passed COM path as the target.
    person_com_weight: float = 0.0
    #: Rate (per frame) at which the G1's offset from the person's COM is followed
    #: (``Problem.com_offset_rate``; 0: the person's COM itself is the target).
    person_offset_rate: float = 0.04
    #: Low-pass the person's COM at ``cutoff_hz`` (zero phase) before it is a target: the
    #: capture's own jitter (part rotations) is not the person's balance.
    person_lowpass: bool = True


def person_com_problem(problem: Problem, demo, mode: str, cfg: BalanceConfig) -> Problem:
    """``problem`` whose first solve holds the G1's horizontal COM on the person's (``demo``
    at the problem's rate, retargeted in ``mode``; the person's COM from
    ``HumanSurface.centre_of_mass``, × the mode's scale as every demonstrated position);
    ``problem`` itself when ``person_com_weight`` is 0."""
    if cfg.person_com_weight == 0.0:
        return problem
    if not cfg.person_com_weight > 0.0:
        raise ValueError(f"balance.person_com_weight must be >= 0, got {cfg.person_com_weight}")
    if demo.num_frames != problem.num_frames:
        raise ValueError(f"{demo.name}: {demo.num_frames} frames, the problem has {problem.num_frames}")
    from retarget.solver.problem import mode_scale

    com = demo.surface.centre_of_mass(demo.part_pos_w, demo.part_quat_w) * mode_scale(demo, mode)
    target = balance_target(com, problem.fps, cfg) if cfg.person_lowpass else com
    w = float(cfg.person_com_weight)
    return replace(problem, com_target=target, com_weight=(w, w, 0.0), com_offset_rate=cfg.person_offset_rate)


def balance_target(com: np.ndarray, fps: float, cfg: BalanceConfig) -> np.ndarray:
    """(T, 3) m, world: ``com`` (T, 3) low-passed at ``cfg.cutoff_hz`` (zero phase)."""
    com = np.asarray(com, np.float64)
    if com.ndim != 2 or com.shape[1] != 3 or not np.isfinite(com).all():
        raise ValueError(f"com must be a finite (T, 3) array, got shape {com.shape}")
    if not cfg.cutoff_hz > 0:
        raise ValueError(f"balance.cutoff_hz must be > 0, got {cfg.cutoff_hz}")
    if cfg.cutoff_hz >= fps / 2 or len(com) < 4:
        return com.copy()  # nothing above the cut-off to remove (or too short to filter)
    return lowpass(com, cfg.cutoff_hz, fps)


def balance_problem(problem: Problem, solution: Solution, balance: BalanceConfig,
                    flight: FlightConfig) -> tuple[Problem, dict] | None:
    """(the pass-2 ``Problem`` after the first ``solution``, statistics); None when neither
    ``balance`` nor ``flight`` asks for a second pass (flight: only a clip that leaves its
    supports). See the module doc."""
    from retarget.solver.residuals import FIXED

    com = com_path(problem.kin.model, robot.qpos_mujoco_to_pinocchio(solution.qpos))
    target, stats = com, {}
    axes, thrown = np.ones(3), False
    if balance.enabled:
        target = balance_target(com, problem.fps, balance)
        if not balance.vertical:
            target[:, 2], axes[2] = com[:, 2], 0.0
        stats["balance"] = True
    if flight.enabled:
        supports = [c for c, track in enumerate(problem.channels) if track.body == FIXED]
        airborne = ~supported_frames(solution.contacts, supports, flight.contact_m)
        if airborne[1:-1].any():
            target = ballistic_com(target, airborne, problem.fps, flight)
            stats["flight_frames"] = int(airborne.sum())
            axes[2], thrown = 1.0, True  # a throw is vertical
    if not stats:
        return None
    shift = target - com
    stats["com_shift_max_m"] = float(np.linalg.norm(shift, axis=1).max())
    # the body moves over its feet; a thrown body takes them along
    moved = np.where(np.isin(problem.style.links, LEG_LINKS) & ~thrown, 0.0, 1.0)
    style = replace(problem.style, pos_w=problem.style.pos_w + moved[None, :, None] * shift[:, None, :])
    weight = (balance.com_weight if balance.enabled else flight.com_weight) * axes
    return replace(problem, style=style, com_target=target, com_weight=tuple(weight.tolist()),
                   com_offset_rate=0.0), stats
