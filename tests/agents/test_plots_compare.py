"""Runs compared at equal learning time: the cumulative learning minutes read from a run's
TensorBoard events, and the side-by-side figure of several runs."""

from __future__ import annotations

import numpy as np
import pytest
from torch.utils.tensorboard import SummaryWriter

from agents import plots
from agents.runs import RunError
from otr_gym import cli


def _fake_run(path, collection_s, learning_s, success):
    """A run folder with rsl-rl's per-iteration timing curves and one metric curve."""
    path.mkdir(parents=True)
    with SummaryWriter(str(path)) as w:
        for it, (c, u, s) in enumerate(zip(collection_s, learning_s, success, strict=True)):
            w.add_scalar("Perf/collection_time", c, it)
            w.add_scalar("Perf/learning_time", u, it)
            w.add_scalar("metric/success_rate", s, it)
    return path


def test_learning_minutes_accumulate_collection_and_update_time(tmp_path):
    run = _fake_run(tmp_path / "a", [30.0, 45.0, 60.0], [30.0, 15.0, 0.0], [0.1, 0.2, 0.3])
    its, minutes = plots.learning_minutes(plots.read_scalars(run))
    assert its == [0, 1, 2]
    np.testing.assert_allclose(minutes, [1.0, 2.0, 3.0])
    assert plots.training_summary(run)["learning_minutes"] == pytest.approx(3.0)


def test_a_run_without_timing_curves_is_refused_by_name(tmp_path):
    run = tmp_path / "untimed"
    run.mkdir()
    with SummaryWriter(str(run)) as w:
        w.add_scalar("metric/success_rate", 0.5, 0)
    with pytest.raises(RunError, match="untimed.*collection_time"):
        plots.plot_runs([run], tmp_path / "x.png")


def test_runs_are_drawn_against_learning_time(tmp_path, monkeypatch):
    fast = _fake_run(tmp_path / "fast", [6.0] * 4, [0.0] * 4, [0.1, 0.2, 0.3, 0.4])
    slow = _fake_run(tmp_path / "slow", [30.0] * 2, [30.0] * 2, [0.0, 0.5])
    drawn = {}
    real_save = plots.save_figure

    def capture(fig, out_png):
        ax = fig.axes[0]
        drawn["title"] = ax.get_title()
        drawn["lines"] = {ln.get_label(): (list(ln.get_xdata()), list(ln.get_ydata())) for ln in ax.get_lines()}
        return real_save(fig, out_png)

    monkeypatch.setattr(plots, "save_figure", capture)
    png = plots.plot_runs([fast, slow], tmp_path / "compare.png", labels=["fast", "slow"])
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert drawn["title"] == plots.TRAINING_PANELS["metric/success_rate"]
    np.testing.assert_allclose(drawn["lines"]["fast"][0], [0.1, 0.2, 0.3, 0.4])  # 6 s an iteration
    np.testing.assert_allclose(drawn["lines"]["slow"][0], [1.0, 2.0])            # 60 s an iteration
    np.testing.assert_allclose(drawn["lines"]["slow"][1], [0.0, 0.5])
    with pytest.raises(ValueError, match="1 labels for 2 runs"):
        plots.plot_runs([fast, slow], tmp_path / "y.png", labels=["one"])


def test_the_cli_compares_several_runs_and_keeps_json_to_one(tmp_path, capsys):
    a = _fake_run(tmp_path / "a", [6.0] * 2, [0.0] * 2, [0.1, 0.2])
    b = _fake_run(tmp_path / "b", [6.0] * 2, [0.0] * 2, [0.3, 0.4])
    assert cli.main(["plot", str(a), str(b), "--png", str(tmp_path / "ab.png")]) == 0
    assert (tmp_path / "ab.png").stat().st_size > 0
    assert cli.main(["plot", str(a), str(b), "--png", str(tmp_path / "c.png"), "--json", str(tmp_path / "c.json")]) == 2
    assert "one run" in capsys.readouterr().err


def test_runs_are_drawn_against_the_iteration_when_asked(tmp_path, monkeypatch):
    fast = _fake_run(tmp_path / "fast", [6.0] * 4, [0.0] * 4, [0.1, 0.2, 0.3, 0.4])
    untimed = tmp_path / "untimed"  # no timing curves: fine on the iteration axis
    untimed.mkdir()
    with SummaryWriter(str(untimed)) as w:
        for it, s in enumerate([0.0, 0.5]):
            w.add_scalar("metric/success_rate", s, it)
    drawn = {}
    real_save = plots.save_figure

    def capture(fig, out_png):
        ax = fig.axes[0]
        drawn["xlabel"] = ax.get_xlabel()
        drawn["lines"] = {ln.get_label(): list(ln.get_xdata()) for ln in ax.get_lines()}
        return real_save(fig, out_png)

    monkeypatch.setattr(plots, "save_figure", capture)
    plots.plot_runs([fast, untimed], tmp_path / "it.png", labels=["fast", "untimed"], x="iteration")
    assert drawn["xlabel"] == "iteration"
    assert drawn["lines"] == {"fast": [0, 1, 2, 3], "untimed": [0, 1]}
    with pytest.raises(ValueError, match="x axis 'steps'"):
        plots.plot_runs([fast], tmp_path / "z.png", x="steps")
    assert cli.main(["plot", str(fast), str(untimed), "--x", "iteration", "--png", str(tmp_path / "cli.png")]) == 0
    assert drawn["lines"]["untimed"] == [0, 1]
