"""The numba kernel warm-up: the list is current, a warm-up fills numba's cache so that the
solver compiles nothing, and stale or malformed entries are reported, never fatal."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from retarget.geometry import kernel_warmup
from retarget.geometry.kernel_warmup import (
    KERNEL_LIST,
    compile_kernels,
    parse_kernel_lines,
    read_kernel_list,
    start_warmup,
)

from conftest import REPO_ROOT

ROOT = REPO_ROOT

# A retarget of the recorded clip that reports the kernels numba compiled (not loaded from its
# cache) and the list's lines for every kernel it called.
_RETARGET_AND_REPORT = textwrap.dedent("""
    import json
    from numba.core import event
    from retarget.cli.kernel_record import retarget_recorded_clip
    from retarget.geometry.kernel_warmup import compiled_signatures

    compiled = []

    class Compiled(event.Listener):
        def on_start(self, e):
            pass

        def on_end(self, e):
            compiled.append(e.data["dispatcher"].py_func.__module__ + "." + e.data["dispatcher"].py_func.__name__)

    event.register("numba:compile", Compiled())
    retarget_recorded_clip()
    print(json.dumps({"compiled": sorted(set(compiled)), "signatures": compiled_signatures()}))
""")

_WARM_UP = textwrap.dedent("""
    import json
    from retarget.geometry import kernel_warmup
    warmup = kernel_warmup.start_warmup()
    failures = kernel_warmup.finish_warmup()
    print(json.dumps({"workers": len(warmup.processes), "failures": failures,
                      "marker": kernel_warmup.warmup_marker().is_file(),
                      "again": kernel_warmup.start_warmup() is None}))
""")


def _run(code: str, numba_cache: Path) -> dict:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(numba_cache), "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_a_warmup_fills_numbas_cache_so_that_the_solver_compiles_nothing_and_the_list_is_current(tmp_path):
    if kernel_warmup._available_cpus() < 2:
        pytest.skip("one CPU: the warm-up never spawns")
    warm = _run(_WARM_UP, tmp_path / "numba")
    assert warm["workers"] >= 1 and warm["failures"] == []
    assert warm["marker"] and warm["again"]  # a filled cache is not warmed twice
    run = _run(_RETARGET_AND_REPORT, tmp_path / "numba")
    listed = [line for line in KERNEL_LIST.read_text().splitlines() if line and not line.startswith("#")]
    assert run["signatures"] == listed, ("retarget/geometry/kernels.txt is stale: otr kernels")
    assert run["compiled"] == [], f"compiled although warmed up: {run['compiled']}"


def test_the_list_parses_into_one_signature_per_kernel_of_this_package():
    entries = read_kernel_list()
    assert len(entries) >= 20
    names = [f"{e.module}.{e.name}" for e in entries]
    assert len(set(names)) == len(names)
    for entry in entries:
        assert entry.module.split(".")[0] in ("retarget", "otr_gym")
        assert callable(entry.dispatcher().compile) and len(entry.signature) >= 1


def test_a_malformed_line_is_refused_with_its_file_and_line_number():
    with pytest.raises(ValueError, match=r"kernels\.txt:3: not a kernel signature"):
        parse_kernel_lines(["# comment", "", "retarget.solver.targets._inside_box (Array(float64, 2, 'C'),"],
                           "kernels.txt")
    with pytest.raises(ValueError, match=r"list\.txt:1: .*NameError"):
        parse_kernel_lines(["retarget.solver.targets._inside_box (os.system('true'),)"], "list.txt")


def test_a_stale_signature_is_reported_by_kernel_name_and_the_others_still_compile():
    stale, good = parse_kernel_lines([
        "retarget.solver.targets._inside_box (float64, float64, float64, float64)",  # arrays changed to scalars
        [line for line in KERNEL_LIST.read_text().splitlines()
         if line.startswith("retarget.solver.targets._inside_box ")][0],
    ], "test")
    failures = compile_kernels([stale, good])
    assert len(failures) == 1 and failures[0].startswith("retarget.solver.targets._inside_box: TypingError")
    assert good.signature in good.dispatcher().signatures


def test_no_warmup_with_one_cpu_and_nothing_to_finish_when_none_began(monkeypatch):
    monkeypatch.setattr(kernel_warmup, "_available_cpus", lambda: 1)
    assert start_warmup() is None
    assert kernel_warmup.finish_warmup() is None


def test_a_missing_kernel_list_skips_the_warmup_with_a_warning_naming_it(tmp_path, monkeypatch):
    monkeypatch.setattr(kernel_warmup, "_available_cpus", lambda: 2)
    monkeypatch.setattr(kernel_warmup, "KERNEL_LIST", tmp_path / "kernels.txt")
    with pytest.warns(RuntimeWarning, match=r"warm-up skipped: .*kernels\.txt"):
        assert start_warmup() is None
    assert kernel_warmup._pending is None


def test_the_marker_changes_with_a_kernel_source(tmp_path, monkeypatch):
    before = kernel_warmup.warmup_marker()
    source = tmp_path / "retarget" / "rows.py"
    source.parent.mkdir()
    source.write_text("x = 1\n")
    (tmp_path / "kernels.txt").write_text("")
    monkeypatch.setattr(kernel_warmup, "_ROOT", tmp_path)
    monkeypatch.setattr(kernel_warmup, "KERNEL_LIST", tmp_path / "kernels.txt")
    first = kernel_warmup.warmup_marker().name
    source.write_text("x = 2  # edited\n")
    assert kernel_warmup.warmup_marker().name != first != before.name
