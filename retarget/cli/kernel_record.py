"""Record the list of numba kernels that ``retarget.geometry.kernel_warmup`` compiles beside a first run.

``otr kernels`` retargets the synthetic box carry in a fresh process and writes every kernel it
called, with its signature, to ``retarget/geometry/kernels.txt``. The carry calls every kernel that
the real carries, tables and walks call, with the same signatures (checked on OMOMO
``sub3_largebox_003`` and ``sub2_largetable_004`` and AMASS ``smplh_walk_jog_turn``). Run it after
changing a kernel's arguments: ``tests/retarget/geometry/test_kernel_warmup.py`` fails while the
list is stale. ``--compile`` compiles the listed kernels into numba's cache now, in this process.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from retarget.geometry.kernel_warmup import KERNEL_LIST, compile_kernels, compiled_signatures, read_kernel_list

#: The clip the list is recorded from: the synthetic box carry at this rate (Hz).
RECORD_FPS = 10.0

_HEADER = ("# numba kernels of the retargeter that Python calls, one signature each (numba's type reprs).\n"
           "# retarget.geometry.kernel_warmup compiles them beside the grids of a first run.\n"
           "# Regenerate after changing a kernel's arguments: otr kernels\n")


def retarget_recorded_clip() -> None:
    """Retarget the clip the list is recorded from (its kernels compile or load in this process)."""
    from retarget.clip import retarget_timed
    from retarget.config import RetargetConfig
    from retarget.inputs.synthetic import generate

    retarget_timed(generate("box_carry"), dataclasses.replace(RetargetConfig(), fps=RECORD_FPS))


def record(path: Path = KERNEL_LIST) -> list[str]:
    """Retarget the recorded clip and write the kernels it called to ``path`` (atomically); run it
    in a fresh process, where nothing else has compiled them."""
    from otr_gym.io import atomic_write

    retarget_recorded_clip()
    lines = compiled_signatures()
    atomic_write(path, lambda f: f.write(_HEADER + "\n".join(lines) + "\n"), binary=False)
    return lines


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """``otr kernels``' arguments."""
    parser.add_argument("--compile", action="store_true",
                        help="compile the listed kernels into numba's cache instead of recording the list")


def main(args: argparse.Namespace) -> int:
    """``otr kernels``: record the list (run it in a fresh process: ``otr`` is one); ``--compile``:
    compile it, exit code 1 naming the kernels that failed."""
    if args.compile:
        entries = read_kernel_list()
        failures = compile_kernels(entries)
        print("\n".join(failures) or f"all {len(entries)} listed kernels compiled")
        return 1 if failures else 0
    print(f"{KERNEL_LIST}: {len(record())} kernels")
    return 0
