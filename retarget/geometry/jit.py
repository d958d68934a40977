"""How the retargeter's numba helpers are compiled.

Kernels called from Python are ``numba.njit(cache=True)``. Functions called only from other
kernels are :data:`helper` or :data:`inlined`: compiled without the CPython and C entry points
that only a call from Python would use (~40 ms of compilation each on a fresh machine's first
run, for nothing once the kernels are cached). The small ones on the per-point paths (grid
cells and their prefetches, poses, a point in a channel's frame) are inlined into their callers
by numba: compiled apart, each call costs a function call that the carry's per-frame time
measurably pays (~1 ms a frame); numba's inlining of the others only lengthened compilation.
"""

from __future__ import annotations

import numba
import numpy as np

#: Decorator of a numba function called only from other numba functions (cached on disk).
helper = numba.njit(cache=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
#: The same, for small helpers on per-point paths: numba inlines them at every call site.
inlined = numba.njit(cache=True, inline="always", no_cpython_wrapper=True, no_cfunc_wrapper=True)


def kernel_pose(a) -> np.ndarray:
    """A small pose array (a rotation, a position, frame origins) as the kernels take it: a
    writeable C-ordered float64 copy. numba types a read-only, strided or F-ordered array as
    another type, so passing one as it comes (the link frames are read-only views) would compile
    the kernel a second time."""
    return np.array(a, np.float64, order="C")
