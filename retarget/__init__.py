"""OTRetarget: demonstrations to G1 references.

Bit-for-bit reproducibility: ProxQP (``proxsuite``) ships three builds of its extension, a
portable one and two vectorised for AVX2 and AVX-512, and imports the widest the CPU runs. The
vectorised builds answer the same QP differently in the last bits depending on where their own
buffers land in memory (the 55 QPs of a 16-frame walk, replayed by 8 fresh workspaces after
different allocations in one process: 2-4 different answers with the AVX-512 build, one with
the portable build), so a reference depended on the process's allocation history: its hash
seed and the clips retargeted before it. Importing this package therefore makes proxsuite load
its portable build: an import of a module whose ``sys.modules`` entry is None fails, and
proxsuite then falls back to the next build. Measured: QP solves are 4-6 % of a frame's time,
the portable build's within the noise of the AVX-512 build's. ``proxqp_build()`` names the build
in use (``tests/test_determinism.py``).
"""

from __future__ import annotations

import sys
import warnings

#: proxsuite's vectorised extension builds, whose results depend on where their buffers land in memory.
VECTORISED_PROXQP = ("proxsuite.proxsuite_pywrap_avx512", "proxsuite.proxsuite_pywrap_avx2")


def _use_portable_proxqp() -> None:
    loaded = [name for name in VECTORISED_PROXQP if sys.modules.get(name) is not None]
    if loaded:
        warnings.warn(f"{loaded[0]} was imported before retarget: retargeting results depend on where ProxQP's "
                      "buffers land in memory and are not bit-for-bit reproducible between processes",
                      RuntimeWarning, stacklevel=3)
        return
    for name in VECTORISED_PROXQP:
        sys.modules.setdefault(name, None)


def proxqp_build() -> str:
    """The module name of the ProxQP extension in use (imports proxsuite)."""
    from proxsuite import proxqp

    return proxqp.__name__.rpartition(".")[0]


_use_portable_proxqp()
