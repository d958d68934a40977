"""Ballistic flights: a second solve that throws the G1's centre of mass through the air.

A person's leap is ballistic; the retargeted robot's, following the person's pelvis, link
poses and contacts, is not: on the AMASS jog the G1's centre of mass leaves the floor at
1.31 m/s and keeps climbing into mid-flight, where a throw to the same landing needs 2.51 m/s,
and speeds up 1.1 m/s forward in the air (``otr verify``: "not ballistic in the
air", 112 / 56 / 75 % of the weight unsupported on average in its three flights). A tracking
policy cannot float, and the jog's policies make their largest errors in and before that leap.

The fix is a second pass over the clip (``retarget.clip.retarget_timed``), only for clips
whose first solution has a flight:

1. **Flight** (``supported_frames``): no G1 link within ``contact_m`` of the ground or of a
   static object (the solution's own contact distances; a held object supports nothing).
2. **Target** (``ballistic_com``): one least-squares solve per world axis over the whole clip:
   the first solution's COM on supported frames (weight 1), its second differences elsewhere
   (``smooth_weight``) and, on flight frames, the second difference of a throw, g·dt²
   (``ballistic_weight``). The take-off and landing frames stay put, so the flight between
   them is a parabola and the push-off before it spreads over the stance frames that lead in.
3. **Pass 2** (``retarget.solver.balance.balance_problem``, which also smooths the COM): every
   style position target (pelvis, torso, hands, feet, …) moves by the COM's correction c* − c,
   so the warm start, the pelvis step bound (``SolverConfig.base_step_m``) and the style terms
   follow the thrown body, and the cost gains ``com_weight``·‖com(q) − c*_t‖² (Pinocchio's
   COM and its Jacobian on the solver's tangent; ``retarget.solver.qp``). Without the shifted
   targets the pelvis step bound (8 mm per frame off the pelvis target's path) held the body
   back and landings came 3 frames late.

Frames: world, z up, g = 9.81 m/s² along −z. COM in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

GRAVITY_M_S2 = np.array([0.0, 0.0, -9.81])


@dataclass(frozen=True)
class FlightConfig:
    """The ballistic second pass (ours; the paper retargets poses and contacts only)."""

    #: Run the second pass on clips whose first solution leaves the ground. Off by default:
    #: on the jog it made the flights ballistic but the policy trained on it tracked no better
    #: (100 %, 47.7 mm against 45.4 mm, one 19-minute run each; docs/results/real_mocap.md), and it
    #: doubles such a clip's solve time.
    enabled: bool = False
    #: A frame is supported while some link is this close to the ground or a static object (m;
    #: ``retarget.checks.feasibility``'s contact height).
    contact_m: float = 0.02
    #: Weight of ‖com(q) − c*‖² in pass 2 (per m²). On the jog (2026-11-27) the COM of pass 2
    #: stays within 1.8 mm of c* (0.1 mm on average) with the style targets moved along.
    com_weight: float = 1.0e4
    #: Weight of the first solution's second differences off flight, against 1 on its positions
    #: at supported frames: how freely the lead-in stance frames may change to push off.
    smooth_weight: float = 10.0
    #: Weight of the throw's second difference g·dt² on flight frames.
    ballistic_weight: float = 1.0e4


def supported_frames(contacts: np.ndarray, supports: np.ndarray, contact_m: float) -> np.ndarray:
    """(T,) bool: some link within ``contact_m`` of a supporting channel.

    ``contacts`` (T, L, C): each link's smallest distance to each channel (m; the solver's
    ``Solution.contacts``), ``supports`` the channel indices that can carry the robot (the
    ground and static objects)."""
    if contacts.ndim != 3:
        raise ValueError(f"contacts must be (T, L, C), got shape {contacts.shape}")
    return (contacts[:, :, np.asarray(supports, np.intp)] < contact_m).any(axis=(1, 2))


def _second_difference(T: int, rows: np.ndarray) -> sp.csr_matrix:
    """Rows t ∈ ``rows`` (1 ≤ t ≤ T − 2) of the second difference x_{t−1} − 2x_t + x_{t+1}."""
    k = len(rows)
    r = np.repeat(np.arange(k), 3)
    c = (rows[:, None] + np.array([-1, 0, 1])).ravel()
    v = np.tile([1.0, -2.0, 1.0], k)
    return sp.csr_matrix((v, (r, c)), shape=(k, T))


def ballistic_com(com: np.ndarray, flight: np.ndarray, fps: float, cfg: FlightConfig = FlightConfig()) -> np.ndarray:
    """(T, 3) m, world: the COM path c* closest to ``com`` (T, 3) whose flight frames
    (``flight`` (T,) bool) accelerate at g (see the module doc). Without a flight frame inside
    the clip it is ``com`` itself."""
    com = np.asarray(com, np.float64)
    T = len(com)
    if com.shape != (T, 3) or not np.isfinite(com).all():
        raise ValueError(f"com must be a finite (T, 3) array, got shape {com.shape}")
    flight = np.asarray(flight, bool)
    if flight.shape != (T,):
        raise ValueError(f"flight must be (T,) = ({T},), got shape {flight.shape}")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    interior = np.arange(1, T - 1)
    airborne = interior[flight[1:-1]]
    if len(airborne) == 0:
        return com.copy()
    ground = interior[~flight[1:-1]]
    held = np.flatnonzero(~flight)
    if len(held) < 2:  # the throws fix the path up to a line, which two anchored frames pin
        raise ValueError(f"a ballistic COM path needs two supported frames, got {len(held)} of {T}")
    dt = 1.0 / fps
    d_air, d_ground = _second_difference(T, airborne), _second_difference(T, ground)
    anchor = sp.csr_matrix((np.ones(len(held)), (np.arange(len(held)), held)), shape=(len(held), T))
    w_air, w_ground = np.sqrt(cfg.ballistic_weight), np.sqrt(cfg.smooth_weight)
    A = sp.vstack([anchor, w_ground * d_ground, w_air * d_air]).tocsc()
    b = np.concatenate([com[held], w_ground * (d_ground @ com),
                        w_air * np.broadcast_to(GRAVITY_M_S2 * dt * dt, (len(airborne), 3))])
    normal = (A.T @ A).tocsc()
    return np.column_stack([spsolve(normal, A.T @ b[:, k]) for k in range(3)])
