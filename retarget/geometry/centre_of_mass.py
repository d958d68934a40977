"""The G1's centre of mass over a clip and as a residual row of the SQP (``retarget.solver.flight``'s
second pass). World frame, metres; configurations in Pinocchio's order (free flyer xyz, xyzw
quaternion, joints)."""

from __future__ import annotations

import numpy as np
import pinocchio as pin


def com_path(model: pin.Model, q: np.ndarray) -> np.ndarray:
    """(T, 3) m, world: the centre of mass of Pinocchio configurations ``q`` (T, nq)."""
    data = model.createData()
    return np.array([pin.centerOfMass(model, data, qt).copy() for qt in q])


def com_residual(model: pin.Model, data: pin.Data, q: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(com(q) − target (3,) m, its Jacobian (3, nv) on Pinocchio's tangent: base twist in the
    base frame, then joints), the solver's own retraction ``pin.integrate``."""
    jac = pin.jacobianCenterOfMass(model, data, q)
    return data.com[0] - target, jac
