"""The evaluation pipeline and the `egcbf eval` command (short episodes, small swarms)."""

import json

import pytest
import torch
from typer.testing import CliRunner

from egcbf.cli import app
from egcbf.control.controllers import make_controller
from egcbf.evaluate.episodes import episode_seed, evaluate
from egcbf.viz.render import render_gif, render_topdown

KEYS = {"num_agents", "safe_rate", "reach_rate", "success_rate", "cost", "cost_min", "cost_max", "reward"}


def test_eval_command_writes_metrics_and_renders(tmp_path):
    out = tmp_path / "ev"
    res = CliRunner().invoke(
        app,
        [
            "eval",
            "--controller",
            "nominal",
            "--num-agents",
            "3,5",
            "--area",
            "2",
            "--episodes",
            "2",
            "--max-steps",
            "12",
            "--out",
            str(out),
            "--render",
            "--no-progress",
        ],
    )
    assert res.exit_code == 0, res.output
    rows = json.loads((out / "metrics.json").read_text())
    assert [r["num_agents"] for r in rows] == [3, 5]
    for r in rows:
        assert KEYS <= set(r) and "step_ms_median" in r
        for k in ("safe_rate", "reach_rate", "success_rate"):
            assert 0.0 <= r[k] <= 1.0
        assert r["cost_min"] <= r["cost"] <= r["cost_max"]
    assert (out / "nominal_N3.gif").stat().st_size > 0
    assert (out / "nominal_N5_topdown.png").stat().st_size > 0
    assert "Safe%" in res.output


@pytest.mark.parametrize(
    "args, message",
    [
        (["--num-agents", "0"], "positive"),
        (["--num-agents", "a,b"], "comma-separated"),
        (["--controller", "nope"], "controller"),
        (["--episodes", "0"], "episodes"),
    ],
)
def test_eval_command_rejects_bad_options(tmp_path, args, message):
    res = CliRunner().invoke(app, ["eval", "--out", str(tmp_path), "--no-progress", *args])
    assert res.exit_code != 0
    assert message in res.output


def test_results_do_not_depend_on_batching():
    kw = dict(area_size=2.0, episodes=3, seed=7, max_steps=15, show_progress=False)
    rows1, _ = evaluate(lambda cfg: make_controller("nominal"), [4], batch=1, **kw)
    rows3, _ = evaluate(lambda cfg: make_controller("nominal"), [4], batch=3, **kw)
    for k in KEYS:
        assert rows1[0][k] == pytest.approx(rows3[0][k], abs=1e-9)


def test_episode_seeds_are_distinct():
    seeds = {episode_seed(0, n, e) for n in (8, 16, 64) for e in range(50)}
    assert len(seeds) == 150


def test_render_rejects_bad_shapes(tmp_path):
    with pytest.raises(ValueError, match="trajectory"):
        render_topdown(tmp_path / "a.png", torch.zeros(5, 3))
    with pytest.raises(ValueError, match="NaN"):
        render_gif(tmp_path / "a.gif", torch.full((2, 3, 3), float("nan")))
    with pytest.raises(ValueError, match="radii"):
        render_topdown(tmp_path / "a.png", torch.zeros(2, 3, 3), centers=torch.zeros(2, 3), radii=torch.ones(1))


def test_version_is_one_source_and_python_m_runs_the_command():
    import subprocess
    import sys

    import egcbf
    import groupcanon

    assert egcbf.__version__ == groupcanon.__version__
    res = subprocess.run([sys.executable, "-m", "egcbf", "--version"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.startswith(f"egcbf {egcbf.__version__} ")
    res = subprocess.run([sys.executable, "-m", "egcbf", "eval", "--episodes", "x"], capture_output=True, text=True,
                         timeout=120)  # fmt: skip
    assert res.returncode == 2 and res.stderr.startswith("Error: ") and "--episodes" in res.stderr


def test_eval_resume_keeps_the_finished_sizes_and_evaluates_the_rest(tmp_path):
    """An interrupted eval continues with --resume: the sizes in run.json's finished list are kept (not rerun),
    the others evaluated, and the result equals the uninterrupted run's; other settings or --overwrite refused."""
    base = ["eval", "--num-agents", "4,6", "--episodes", "2", "--max-steps", "5", "--no-progress"]
    full, part = tmp_path / "full", tmp_path / "part"
    assert CliRunner().invoke(app, [*base, "--out", str(full)]).exit_code == 0
    assert CliRunner().invoke(app, [*base, "--out", str(part)]).exit_code == 0
    rows = json.loads((part / "metrics.json").read_text())
    run = json.loads((part / "run.json").read_text())
    kept = {**rows[0], "safe_rate": -1.0}  # a marker: a kept size is read back, not recomputed
    (part / "metrics.json").write_text(json.dumps([kept]))
    (part / "run.json").write_text(json.dumps({**run, "finished": [4], "complete": False}))
    res = CliRunner().invoke(app, [*base, "--out", str(part), "--resume"])
    assert res.exit_code == 0, res.output
    got, want = json.loads((part / "metrics.json").read_text()), json.loads((full / "metrics.json").read_text())
    assert got[0]["safe_rate"] == -1.0 and [r["num_agents"] for r in got] == [4, 6]
    drop = ("step_ms_median",)
    assert {k: v for k, v in got[1].items() if k not in drop} == {k: v for k, v in want[1].items() if k not in drop}
    assert json.loads((part / "run.json").read_text())["complete"] is True
    for extra, says in ((["--episodes", "3"], "other settings (episodes)"), (["--overwrite"], "pass one"),
                        (["--out", str(tmp_path / "none")], "does not exist")):  # fmt: skip
        args = [*base, "--out", str(part), "--resume", *extra]
        res = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
        assert res.exit_code == 2 and says in res.output, res.output
