"""Style costs (paper Sec. III-D, eq. m-esty-o): the human skeleton as a posture prior.

Robot: for the tracked links ℓ (``retarget.inputs.human.STYLE_LINKS``) the orientation target is
R̂_ℓ = R_h(ℓ) O_ℓ (human part world orientation × T-pose alignment offset). Position targets
align the pelvises, then run forward kinematics over the *G1's own* link offsets with the
desired orientations, so targets never ask the robot to stretch to human bone lengths.
Links between tracked ones (hip pitch/roll, waist, shoulder pitch/roll, wrist roll/pitch,
ankle pitch) borrow the desired orientation of the tracked link below them, composed with
their T-pose relative rotation.

Objects: τ̂, R̂ are the demonstrated object poses.

Residual rows use the world-aligned twist convention of ``retarget.solver.residuals``: a position
row has φ = (e_i, 0); an orientation row of e = log(R R̂ᵀ) has φ = (0, J_l⁻¹(e)_i), since a
world rotation δθ changes e by J_l⁻¹(e) δθ.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from otr_gym import robot
from otr_gym.rotations import (
    quat_mul,
    quat_to_matrix,
    so3_left_jacobian_inverse,
    so3_log,
)
from retarget.geometry.kinematics import LinkFrames, RobotKinematics
from retarget.solver.residuals import FIXED, Rows


@dataclass(frozen=True)
class StyleConfig:
    """Weights of E_sty (eq. m-esty-o). The paper gives no values; ours, with the reasons:

    * ``pos_weight`` λ_pos = 0.1 (per m²): small, as the paper asks in native scale, so contacts
      and not the human-length skeleton place the links (a 20 cm pelvis-height mismatch costs
      0.004, less than a 5 mm foot–ground gap under λ^d = 256). Measured: λ_pos = 1 lost 6–16
      points of ground Jaccard on both clips below.
    * ``rot_weight`` λ_rot = 1 (per rad²): orientations carry the style. Against the paper's
      ‖q_t ⊖ q_{t−1}‖² (weight 1) a link lags a target turning ω rad per frame by ~ω/λ_rot, so
      a small λ_rot lags fast arm swings by tens of degrees; a large one keeps the hands from
      what they must reach. Measured (evaluation protocol, ``retarget.evaluation``; OMOMO
      sub3_largebox_003 native; hand hold on the synthetic box lift, ``retarget.checks.verify``):
      λ_rot 0.5 / 1 / 2 → rot 18.0° / 15.6° / 14.0°, object J 40 % / 55 % / 62 %, ground J
      86 % / 86 % / 86 %, synthetic lift hand hold 97 % / 92 % / 57 %. 1 is the compromise:
      most of the orientation and object-contact gain, without losing the floor-level grasp.
    * ``object_pos_weight`` λ_o,pos = 300 (per m²) and ``object_rot_weight`` λ_o,rot = 1 (per
      rad²): the object stays where the person put it and the robot comes to it. Measured on
      OMOMO sub3_largebox_003 native (evaluation protocol, true-surface meshes, planted feet,
      before the contact-state rows): λ_o,pos 10 / 100 / 300 / 1000 → drift 13.4 / 4.6 / 2.1 /
      0.9 cm; with 10 the small robot pulls the box down to its chest (object precision 55 %);
      300 keeps the drift well under the fidelity target's 5 cm (2.2 cm with the contact-state
      rows, object R/P/J 95/95/91 %).
    """

    pos_weight: float = 0.1
    rot_weight: float = 1.0
    object_pos_weight: float = 300.0
    object_rot_weight: float = 1.0
    #: Ours: in a two-hand hold of the demonstration (``retarget.solver.holds``: both of the
    #: person's hands within ``hold_reach_m`` of the object while it is lifted more than
    #: ``hold_lift_m`` above its lowest height), the object's pose is held to the demonstration
    #: by these weights instead (per m², per rad²; one below the base weight keeps the base),
    #: blended in and out over ``hold_ramp_s``. The frames depend on the demonstration alone,
    #: not on the probe seed (docs/results/box.md, "No lottery").
    hold_pos_weight: float = 300.0
    hold_rot_weight: float = 1.0
    #: ... on box-like objects only (``otr_gym.object_box``: those the grasp pass squeezes and the
    #: box environment collides as a box); other shapes keep the base weights in holds too.
    hold_boxes_only: bool = True
    hold_reach_m: float = 0.05
    hold_lift_m: float = 0.02
    hold_ramp_s: float = 0.3


@dataclass(frozen=True)
class StyleTargets:
    """Desired world poses of the tracked links over a demonstration."""

    links: np.ndarray  # (S,) link indices (BODY_NAMES order)
    pos_w: np.ndarray  # (T, S, 3) m
    rot_w: np.ndarray  # (T, S, 3, 3)


def _style_sources(kin: RobotKinematics, styled: np.ndarray) -> np.ndarray:
    """For every link, the tracked link whose desired orientation it borrows (itself if tracked).

    A link that is not tracked follows its single-child chain down to the first tracked link.
    """
    children = [np.flatnonzero(kin.parents == k) for k in range(len(kin.parents))]
    source = np.full(len(kin.parents), -1)
    for k in range(len(kin.parents)):
        j = k
        while j not in styled:
            if len(children[j]) != 1:
                raise RuntimeError(f"link {robot.BODY_NAMES[k]} has no tracked link below a single chain")
            j = int(children[j][0])
        source[k] = j
    return source


@lru_cache(maxsize=1)
def _pelvis_heights() -> tuple[float, float]:
    """(G1 T-pose pelvis height, mannequin T-pose pelvis height / its stature), soles at z = 0."""
    from retarget.inputs.human import HumanModel, g1_tpose_body_poses, human_tpose

    model = HumanModel()
    pelvis_z = float(human_tpose(model)[0][0, 2])
    return float(g1_tpose_body_poses()[0][0, 2]), pelvis_z / model.stature_m


def pelvis_height_ratio(stature_m: float) -> float:
    """G1 pelvis height / the person's (standing, soles on the floor), from the stature (m).

    The pelvis target's height is the person's times this ratio (ours): with the person's own
    height, a leap lifts the shorter-legged G1 by the person's pelvis rise *plus* the leg-length
    difference (on AMASS walk_jog_turn the G1's soles left the floor by 38 cm where the person's
    left it by 15 cm), and in stance the target pulls the pelvis up against the foot contacts.
    """
    g1, per_stature = _pelvis_heights()
    return g1 / (per_stature * stature_m) if stature_m > 0 else 1.0


def robot_style_targets(part_pos_w: np.ndarray, part_quat_w: np.ndarray, kin: RobotKinematics,
                        pelvis_height_scale: float = 1.0) -> StyleTargets:
    """Targets for every frame from human part poses (T, 22, 3) m / (T, 22, 4) wxyz (world).

    The pelvis position target is the person's with its height × ``pelvis_height_scale``
    (``pelvis_height_ratio``); the other position targets follow by the G1's link lengths."""
    from retarget.inputs.human import (
        STYLE_LINKS,
        alignment_offsets,
        g1_tpose_body_poses,
        part_index,
    )

    links = robot.body_indices(list(STYLE_LINKS))
    parts = part_index(list(STYLE_LINKS.values()))
    offsets = alignment_offsets()
    o = np.stack([offsets[n] for n in STYLE_LINKS])
    rot_styled = quat_to_matrix(quat_mul(part_quat_w[:, parts], o))  # (T, S, 3, 3): R_h(ℓ) O_ℓ

    _, tpose_quat = g1_tpose_body_poses()
    tpose_rot = quat_to_matrix(tpose_quat)
    source = _style_sources(kin, set(links.tolist()))
    slot = {int(k): i for i, k in enumerate(links)}
    T = part_pos_w.shape[0]
    rot_all = np.empty((T, len(source), 3, 3))
    for k, s in enumerate(source):
        relative = tpose_rot[s].T @ tpose_rot[k]  # R_s⁰ᵀ R_k⁰
        rot_all[:, k] = rot_styled[:, slot[int(s)]] @ relative
    pos_all = np.empty((T, len(source), 3))
    for k, parent in enumerate(kin.parents):  # parents precede children in BODY_NAMES order
        if parent < 0:
            pos_all[:, k] = part_pos_w[:, 0] * np.array([1.0, 1.0, pelvis_height_scale])  # pelvises aligned
        else:
            pos_all[:, k] = pos_all[:, parent] + rot_all[:, parent] @ kin.offsets_parent[k]
    return StyleTargets(links, pos_all[:, links], rot_all[:, links])


def robot_style_rows(frames: LinkFrames, links: np.ndarray, pos_target: np.ndarray, rot_target: np.ndarray,
                     cfg: StyleConfig) -> Rows:
    """Rows of λ_pos‖x_ℓ − x̂_ℓ‖² + λ_rot‖log(R_ℓ R̂_ℓᵀ)‖² for the tracked links at one frame."""
    n = len(links)
    return pose_rows(frames.pos[links], frames.rot[links], pos_target, rot_target, links,
                     np.full(n, cfg.pos_weight), np.full(n, cfg.rot_weight))


def object_style_rows(pos: np.ndarray, rot: np.ndarray, pos_target: np.ndarray, rot_target: np.ndarray,
                      body: int, cfg: StyleConfig) -> Rows:
    """Rows of λ_o,pos‖τ − τ̂‖² + λ_o,rot‖log(R R̂ᵀ)‖² for one object."""
    return pose_rows(pos[None], rot[None], pos_target[None], rot_target[None], np.array([body]),
                     np.array([cfg.object_pos_weight]), np.array([cfg.object_rot_weight]))


def pose_rows(pos: np.ndarray, rot: np.ndarray, pos_target: np.ndarray, rot_target: np.ndarray, bodies: np.ndarray,
              pos_weight: np.ndarray, rot_weight: np.ndarray) -> Rows:
    """Rows of Σ_b λ_pos,b‖τ_b − τ̂_b‖² + λ_rot,b‖log(R_b R̂_bᵀ)‖², 6 per body, for n bodies
    (links and objects alike, in one batch): poses (n, 3) m and (n, 3, 3) world, weights (n,)."""
    pos_err = pos - pos_target
    rot_err = so3_log(rot @ np.swapaxes(rot_target, -1, -2))
    n = len(bodies)
    phi = np.zeros((n, 6, 12))
    phi[:, :3, :3] = np.eye(3)
    phi[:, 3:, 3:6] = so3_left_jacobian_inverse(rot_err)
    weight = np.repeat(np.stack([pos_weight, rot_weight], axis=1), 3, axis=1)
    return Rows(np.concatenate([pos_err, rot_err], axis=1).ravel(), weight.ravel(), phi.reshape(-1, 12),
                np.repeat(bodies, 6), np.full(6 * n, FIXED, dtype=np.intp))
