"""Distances and kinematics the solver and the checks share: proximity channels with signed
distance grids, their error margins, the G1's link poses and Jacobians (Pinocchio), the centre of
mass, and the compiled (numba) kernels with their warm-up."""
