"""Style error *rot* (paper Sec. IV-A): link orientations against the style targets.

The target of link ℓ is R̂_ℓ = R_h(ℓ) O_ℓ: the world orientation of its human part times the
fixed alignment offset O_ℓ from the T-poses (``retarget.inputs.human.alignment_offsets``), the same
offsets for every method. The error is the angle of R_ℓ R̂_ℓᵀ.
"""

from __future__ import annotations

import numpy as np

from otr_gym.rotations import quat_error_angle, quat_mul


def orientation_error_deg(link_quat_w: np.ndarray, part_quat_w: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(T, L) angle (deg) between robot link orientations and their style targets.

    link_quat_w, part_quat_w: (T, L, 4) wxyz world; offsets (L, 4) wxyz (O_ℓ, part → link).
    """
    target = quat_mul(part_quat_w, np.broadcast_to(offsets, part_quat_w.shape))
    return np.degrees(quat_error_angle(link_quat_w, target))
