"""The torch paths of otr_gym.rotations (few kernels, for the GPU environments) agree with the NumPy
formulas the retargeter uses, with broadcasting."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from otr_gym import rotations as R


def _unit(rng, shape):
    q = rng.normal(size=(*shape, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 5e-7)])
def test_torch_and_numpy_quaternion_maths_agree(dtype, tol):
    rng = np.random.default_rng(3)
    a, b = _unit(rng, (64, 5)), _unit(rng, (64, 5))
    ta, tb = torch.tensor(a, dtype=dtype), torch.tensor(b, dtype=dtype)
    np.testing.assert_allclose(R.quat_mul(ta, tb).numpy(), R.quat_mul(a, b), atol=tol)
    np.testing.assert_allclose(R.quat_mul(ta[:, :1], tb).numpy(), R.quat_mul(a[:, :1], b), atol=tol)  # broadcast
    np.testing.assert_allclose(R.quat_conj(ta).numpy(), R.quat_conj(a), atol=0)
    np.testing.assert_allclose(R.quat_to_matrix(ta).numpy(), R.quat_to_matrix(a), atol=tol)
    # the matrix is a rotation, and the product composes like the matrices
    m = R.quat_to_matrix(R.quat_mul(ta, tb)).double()
    np.testing.assert_allclose(m.numpy(), (R.quat_to_matrix(ta).double() @ R.quat_to_matrix(tb).double()).numpy(),
                               atol=20 * tol)
    assert R.quat_mul(ta, tb).dtype == dtype
