"""benchmarks/detached.sh: commands that outlive a device call, waited on by process id."""

from __future__ import annotations

import os
import subprocess
import time

import pytest

from conftest import REPO_ROOT

SCRIPT = REPO_ROOT / "benchmarks" / "detached.sh"


@pytest.fixture
def detached(tmp_path):
    env = {**os.environ, "DETACHED_DIR": str(tmp_path / "jobs")}

    def call(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["bash", str(SCRIPT), *args], capture_output=True, text=True, env=env, timeout=60)

    yield call, tmp_path / "jobs"
    for pid in (tmp_path / "jobs").glob("*/pid"):  # nothing outlives the test
        try:
            os.killpg(int(pid.read_text()), 9)
        except (ProcessLookupError, ValueError, PermissionError):
            pass


def test_wait_returns_when_the_jobs_end_with_their_exit_codes_and_log_tails(detached):
    call, jobs = detached
    assert call("start", "ok", "bash", "-c", "sleep 1; echo trained 42").returncode == 0
    assert call("start", "bad", "bash", "-c", "echo no reference >&2; exit 4").returncode == 0
    began = time.monotonic()
    waited = call("wait", "60", "ok", "bad")
    # ended by the jobs, not by the 60 s limit: the wait polls pids, not command lines (which
    # its own shell's would match)
    assert time.monotonic() - began < 30
    assert waited.returncode == 1, waited.stdout  # one job failed
    assert "== ok: exit 0" in waited.stdout and "trained 42" in waited.stdout
    assert "== bad: exit 4" in waited.stdout and "no reference" in waited.stdout
    assert (jobs / "ok" / "rc").read_text().strip() == "0"
    assert call("wait", "5", "ok").returncode == 0


def test_a_running_job_is_reported_running_and_cannot_be_started_twice(detached):
    call, jobs = detached
    assert call("start", "long", "sleep", "30").returncode == 0
    waited = call("wait", "1", "long")
    assert waited.returncode == 3 and "== long: running" in waited.stdout
    again = call("start", "long", "sleep", "1")
    assert again.returncode == 1 and "still running" in again.stderr
    os.killpg(int((jobs / "long" / "pid").read_text()), 9)
    time.sleep(0.5)
    status = call("status", "long")
    assert status.returncode == 1 and "== long: killed" in status.stdout


def test_bad_arguments_are_refused_by_name(detached):
    call, _ = detached
    for args, message in [(("start", "a/b", "true"), "plain name"), (("wait", "soon", "x"), "whole number"),
                          (("start", "x"), "usage"), (("nope",), "usage")]:
        result = call(*args)
        assert result.returncode == 2 and message in result.stderr, (args, result.stderr)
    unknown = call("status", "never_started")
    assert unknown.returncode == 1 and "never_started: unknown" in unknown.stdout
