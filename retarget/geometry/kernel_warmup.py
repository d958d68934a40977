"""Compile the solver's numba kernels in other processes while this one builds the grids.

A fresh machine's first ``otr retarget`` spends ~17 s in numba compiling the solver's kernels
(Python work: one core) and ~15 s building distance grids, one after the other, since each
kernel compiles on its first call, in the first frame. The kernels and the one signature each
is called with are listed in ``retarget/geometry/kernels.txt`` (numba's type reprs). With spare cores,
``otr retarget`` calls :func:`start_warmup` first thing: it spawns processes that compile the
listed kernels, taking them from the front of the list, while this process reads the clip and
builds its grids. numba writes each compiled kernel to its on-disk cache (``cache=True``,
``retarget.geometry.jit``). :func:`finish_warmup`, called before the first frame, compiles the kernels
still left from the back of the list in this process and joins the others: the solver's first
call of each kernel then finds it compiled or loads it from the cache. The reference is the same
either way; only where the compilation runs changes.

Nothing is spawned where it would not help: when this process has compiled the kernels already,
when only one CPU is available to it, when numba's JIT is off, or when a marker says the cache
was filled for these source files and this numba (the marker lives next to numba's cache:
deleting one without the other costs the old, serial compilation, never a wrong kernel, since
numba checks its cache against the sources itself). Library calls never spawn: only the command
line starts a warm-up. A warm-up that fails costs time, never a result: the solver compiles
what it needs, and a warning names the kernel.

``otr kernels`` rewrites the list from a retarget of the synthetic box carry
(``retarget.cli.kernel_record``; the tests check that the list is current).
"""

from __future__ import annotations

import hashlib
import importlib
import multiprocessing
import os
import sys
import traceback
import warnings
from dataclasses import dataclass, field
from pathlib import Path

#: The kernels and their signatures: ``module.function (type, ...)`` per line.
KERNEL_LIST = Path(__file__).with_name("kernels.txt")
#: At most this many warm-up processes (each imports the package and compiles shared helpers).
MAX_WORKERS = 4

_ROOT = Path(__file__).resolve().parents[2]
#: Source files of numba kernels: a change to any of them makes numba recompile (and a new marker).
_KERNEL_SOURCES = ("retarget/**/*.py", "otr_gym/rotations.py")
_PACKAGES = ("retarget", "otr_gym")

_pending: WarmUp | None = None


@dataclass(frozen=True)
class KernelSignature:
    """One listed kernel: its module, function name and argument types (numba types)."""

    module: str
    name: str
    signature: tuple = field(compare=False)
    text: str = ""

    def dispatcher(self):
        return getattr(importlib.import_module(self.module), self.name)


def read_kernel_list(path: Path = KERNEL_LIST) -> list[KernelSignature]:
    """The kernels listed in ``path``; a line that does not parse raises ValueError naming it."""
    return parse_kernel_lines(Path(path).read_text(encoding="utf-8").splitlines(), str(path))


def parse_kernel_lines(lines: list[str], source: str) -> list[KernelSignature]:
    """The kernels of the list's ``lines`` (comments and blank lines skipped), read from ``source``."""
    from numba.core import types

    namespace = {"__builtins__": {}, **vars(types)}
    entries = []
    for number, line in enumerate(lines, start=1):
        if not line.strip() or line.startswith("#"):
            continue
        qualified, _, text = line.partition(" ")
        module, _, name = qualified.rpartition(".")
        try:
            signature = eval(text, namespace)  # noqa: S307 - numba type reprs, names from numba.core.types only
            if not module or not isinstance(signature, tuple):
                raise ValueError("expected 'module.function (type, ...)'")
        except Exception as exc:  # noqa: BLE001 - any malformed line is reported with its place
            raise ValueError(f"{source}:{number}: not a kernel signature ({type(exc).__name__}: {exc}): "
                             f"{line[:120]}") from exc
        entries.append(KernelSignature(module, name, signature, text))
    return entries


def compiled_signatures() -> list[str]:
    """The list's lines for every numba dispatcher of this package that this process compiled."""
    from numba.core.registry import CPUDispatcher

    lines = set()
    for name, module in list(sys.modules.items()):
        if name.split(".")[0] not in _PACKAGES:
            continue
        for attr, value in vars(module).items():
            # helpers (retarget.geometry.jit) compile inside their callers and cannot be called from Python
            if (isinstance(value, CPUDispatcher) and value.__module__ == name
                    and not value.targetoptions.get("no_cpython_wrapper")):
                lines.update(f"{name}.{attr} {signature!r}" for signature in value.signatures)
    return sorted(lines)


def compile_kernels(entries: list[KernelSignature]) -> list[str]:
    """Compile (or load from numba's cache) every entry; the failures, one line each."""
    failures = []
    for entry in entries:
        try:
            entry.dispatcher().compile(entry.signature)
        except Exception as exc:  # noqa: BLE001 - a stale entry must not stop the others
            failures.append(f"{entry.module}.{entry.name}: {type(exc).__name__}: {str(exc).splitlines()[0][:200]}")
    return failures


def warmup_marker() -> Path:
    """The marker of a filled kernel cache for the present sources and numba: next to numba's
    cache (``$NUMBA_CACHE_DIR``, else the ``__pycache__`` folder numba writes beside the sources,
    else the otr-gym cache when that is not writable)."""
    import numba

    digest = hashlib.sha256(f"{numba.__version__}|{sys.version}".encode())
    for path in [*(p for pattern in _KERNEL_SOURCES for p in sorted(_ROOT.glob(pattern))), KERNEL_LIST]:
        st = path.stat()
        digest.update(f"|{path.relative_to(_ROOT)}:{st.st_mtime_ns}:{st.st_size}".encode())
    if numba.config.CACHE_DIR:
        folder = Path(numba.config.CACHE_DIR)
    else:
        folder = _ROOT / "retarget" / "__pycache__"
        if not os.access(folder if folder.is_dir() else folder.parent, os.W_OK):
            from retarget.geometry.cache import default_cache_dir

            folder = default_cache_dir()
    return folder / f"otr-kernels-{digest.hexdigest()[:20]}.warm"


def _available_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


@dataclass
class WarmUp:
    """Running warm-up processes sharing one list: they take kernels from its front, and
    :meth:`wait` from its back (``front`` ≤ ``back``, both under ``lock``)."""

    entries: list[KernelSignature]
    processes: list
    outcomes: list
    front: object
    back: object
    lock: object
    marker: Path

    def wait(self) -> list[str]:
        """Compile what the processes have not taken yet, join them; the kernels that failed
        (a warning names them; the solver compiles them itself). All compiled: the marker is written."""
        from otr_gym.io import atomic_write

        failures = []
        while (k := _take(self.front, self.back, self.lock, from_back=True)) is not None:
            failures += compile_kernels([self.entries[k]])
        for process, outcome in zip(self.processes, self.outcomes):
            process.join()
            failures += outcome.recv() if outcome.poll() else [f"warm-up process: exit code {process.exitcode}"]
            outcome.close()
        if failures:
            warnings.warn("numba kernel warm-up: " + "; ".join(failures) + " (the solver compiles them itself; "
                          "if a signature is stale: otr kernels)",
                          RuntimeWarning, stacklevel=2)
        else:
            self.marker.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(self.marker, lambda f: f.write(b"otr-gym retarget kernels are in numba's cache\n"))
        return failures

    def stop(self) -> None:
        """End the processes without waiting (numba replaces its cache files atomically)."""
        for process in self.processes:
            process.terminate()
            process.join()


def start_warmup() -> WarmUp | None:
    """Spawn the warm-up processes (one per spare CPU, at most ``MAX_WORKERS``) and keep them
    for :func:`finish_warmup`; None where they would not help (see the module doc)."""
    global _pending
    import numba

    if _pending is not None or numba.config.DISABLE_JIT or _available_cpus() < 2:
        return None
    try:
        entries = read_kernel_list(KERNEL_LIST)
    except (OSError, ValueError) as exc:  # a missing or broken list costs the warm-up, never the run
        warnings.warn(f"numba kernel warm-up skipped: {exc}", RuntimeWarning, stacklevel=2)
        return None
    from retarget.geometry.kinematics import _link_jacobians

    if _link_jacobians.signatures:  # this process compiled the kernels already (a previous clip)
        return None
    marker = warmup_marker()
    if marker.is_file():
        return None
    context = multiprocessing.get_context("spawn")
    lock = context.Lock()
    front, back = context.Value("i", 0, lock=False), context.Value("i", len(entries), lock=False)
    processes, outcomes = [], []
    for k in range(min(MAX_WORKERS, _available_cpus() - 1)):
        receive, send = context.Pipe(duplex=False)
        process = context.Process(target=_compile_from_front, args=(KERNEL_LIST, front, back, lock, send),
                                  name=f"otr-kernel-warmup-{k}", daemon=True)
        process.start()
        send.close()
        processes.append(process)
        outcomes.append(receive)
    _pending = WarmUp(entries, processes, outcomes, front, back, lock, marker)
    return _pending


def finish_warmup() -> list[str] | None:
    """Finish the warm-up that :func:`start_warmup` began (its failures), if one is pending."""
    global _pending
    warmup, _pending = _pending, None
    return None if warmup is None else warmup.wait()


def stop_warmup() -> None:
    """End a pending warm-up without waiting for it (the command is done or failed)."""
    global _pending
    warmup, _pending = _pending, None
    if warmup is not None:
        warmup.stop()


def _take(front, back, lock, from_back: bool) -> int | None:
    """The index of the next kernel nobody has taken, from the front or the back of the shared
    list (None once the two ends meet)."""
    with lock:
        if front.value >= back.value:
            return None
        if from_back:
            back.value -= 1
            return back.value
        front.value += 1
        return front.value - 1


def _compile_from_front(path, front, back, lock, send) -> None:
    """A warm-up process: compile the list's kernels from the front until it meets the back;
    the failures go back through ``send``."""
    failures = []
    try:
        entries = read_kernel_list(path)
        while (k := _take(front, back, lock, from_back=False)) is not None:
            failures += compile_kernels([entries[k]])
    except BaseException as exc:  # noqa: BLE001 - every failure goes back to the parent, which carries on
        failures.append(f"warm-up process: {type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}")
    finally:
        send.send(failures)
        send.close()
