"""Time alignment of a demonstration to a reference.

Comparisons happen at the **reference's frame times** t_k = k / fps_ref: the robot side is
then exact (its stored poses), and the demonstration (30 fps OMOMO, 120 fps AMASS) is
interpolated there — positions linearly, orientations by slerp — clamped to its last frame
when the reference ends a fraction of a frame later. Both clips start at t = 0.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from otr_gym.rotations import quat_slerp
from retarget.inputs.demonstration import Demonstration


class AlignmentError(ValueError):
    """Reference and demonstration that cannot be compared frame by frame."""


def check_durations(ref_duration_s: float, demo_duration_s: float, tolerance_s: float,
                    ref_name: str, demo_name: str) -> None:
    """Raise AlignmentError naming both files when the clips' durations differ beyond tolerance."""
    gap = ref_duration_s - demo_duration_s
    if abs(gap) > tolerance_s:
        raise AlignmentError(
            f"{ref_name}: lasts {ref_duration_s:.3f} s but its demonstration {demo_name} lasts "
            f"{demo_duration_s:.3f} s ({gap:+.3f} s, tolerance {tolerance_s} s): not the same clip, "
            f"or trimmed")


def _interp_weights(times_s: np.ndarray, fps: float, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x = np.clip(np.asarray(times_s, np.float64) * fps, 0.0, n - 1)
    i0 = np.minimum(np.floor(x).astype(np.int64), n - 1)
    i1 = np.minimum(i0 + 1, n - 1)
    return i0, i1, x - i0


def _lerp(x: np.ndarray, i0, i1, a) -> np.ndarray:
    w = a.reshape((-1,) + (1,) * (x.ndim - 1))
    return (1.0 - w) * x[i0] + w * x[i1]


def _slerp(q: np.ndarray, i0, i1, a) -> np.ndarray:
    w = np.broadcast_to(a.reshape((-1,) + (1,) * (q.ndim - 2)), q[i0].shape[:-1])
    return quat_slerp(q[i0], q[i1], w)


def demo_at_times(demo: Demonstration, times_s: np.ndarray) -> Demonstration:
    """The demonstration's human and object poses at ``times_s`` (s), with ``fps`` kept as the
    nominal rate of the new frames (1 / spacing of ``times_s``)."""
    times_s = np.asarray(times_s, np.float64)
    i0, i1, a = _interp_weights(times_s, demo.fps, demo.num_frames)
    objects = [replace(o, pos_w=_lerp(o.pos_w, i0, i1, a), quat_w=_slerp(o.quat_w, i0, i1, a)) for o in demo.objects]
    fps = 1.0 / float(np.median(np.diff(times_s))) if times_s.size > 1 else demo.fps
    return replace(demo, fps=fps, part_pos_w=_lerp(demo.part_pos_w, i0, i1, a),
                   part_quat_w=_slerp(demo.part_quat_w, i0, i1, a), objects=objects)
