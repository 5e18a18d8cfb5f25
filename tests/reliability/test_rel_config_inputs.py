"""Inputs that used to be accepted and fail later (or be truncated): a training config's evaluation settings, float
seeds, an arena too large for the neighbour grid, obstacles that leave no room."""

import pytest

from egcbf.algo.config import TrainConfig
from egcbf.env import EnvConfig
from egcbf.evaluate.episodes import evaluate


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"eval_area_size": -1.0}, r"evaluation environment.*area_size"),
        ({"eval_num_agents": 0}, r"evaluation environment.*num_agents"),
        ({"eval_num_agents": 2.5}, r"eval_num_agents must be None or an integer"),
        ({"eval_max_steps": 0}, r"evaluation environment.*max_steps"),
        ({"area_sizes": [2.0, 1e12]}, r"training environment.*area_size"),
        ({"seed": 1.5}, r"seed must be an integer"),
        ({"seed": True}, r"seed must be an integer"),
    ],
)
def test_train_config_refuses_what_would_fail_later(change, match):
    with pytest.raises(ValueError, match=match):
        TrainConfig.preset("egcbf+", "tiny", **change)


def test_train_cli_refuses_a_config_with_bad_evaluation_settings_before_training(tmp_path):
    from typer.testing import CliRunner

    from egcbf.cli import app

    f = tmp_path / "c.json"
    f.write_text('{"preset": "tiny", "eval_area_size": 0}')
    res = CliRunner().invoke(app, ["train", "--algo", "egcbf+", "--config", str(f), "--out", str(tmp_path / "run"),
                                   "--no-progress"])  # fmt: skip
    assert res.exit_code == 2, res.output
    assert "evaluation environment" in res.output and "eval_area_size" in res.output
    assert not (tmp_path / "run" / "checkpoints").exists()


@pytest.mark.parametrize(("name", "value"), [("seed", 1.5), ("seed", "0"), ("episodes", 2.0)])
def test_evaluate_refuses_non_integer_seed_and_episodes(name, value):
    kw = {"seed": 0, "episodes": 1, name: value}
    with pytest.raises(TypeError, match=rf"{name} must be an integer"):
        evaluate(lambda cfg: None, [2], area_size=2.0, show_progress=False, **kw)


@pytest.mark.parametrize("sizes", [8, "8", [8.0]])
def test_evaluate_refuses_sizes_that_are_not_a_list_of_integers(sizes):
    with pytest.raises(TypeError, match="num_agents must be a sequence of integers"):
        evaluate(lambda cfg: None, sizes, area_size=2.0, episodes=1, show_progress=False)


def test_an_arena_too_large_for_the_neighbour_grid_is_refused():
    with pytest.raises(ValueError, match=r"area_size must be at most .* comm_radius"):
        EnvConfig(num_agents=8, area_size=1e9)


def test_cli_obstacles_that_leave_no_room_are_a_usage_error(tmp_path):
    from typer.testing import CliRunner

    from egcbf.cli import app

    res = CliRunner().invoke(
        app,
        ["eval", "--controller", "nominal", "--num-agents", "8", "--area", "1", "--obstacles", "5000",
         "--episodes", "1", "--out", str(tmp_path / "o"), "--no-progress"],
    )  # fmt: skip
    assert res.exit_code == 2, res.output
    assert "--obstacles 5000 leave no room" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "o" / "metrics.json").exists()


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        (["--scene", "crossing", "--num-agents", "512", "--area", "2"], "crossing scene's start region of --area 2"),
        (["--num-agents", "1500", "--area", "2"], "no room for --num-agents 1500 in --area 2"),
    ],
)
def test_cli_swarms_below_the_packing_bound_that_cannot_be_sampled_are_a_usage_error(tmp_path, extra, match):
    """The packing bound passes these (it is necessary only); rejection sampling cannot place them: refused up
    front, one line, nothing written."""
    from typer.testing import CliRunner

    from egcbf.cli import app

    res = CliRunner().invoke(
        app,
        ["eval", "--controller", "nominal", *extra, "--episodes", "1", "--out", str(tmp_path / "o"), "--no-progress"],
    )
    assert res.exit_code == 2, res.output
    assert match in res.output and "Traceback" not in res.output
    assert [line for line in res.output.splitlines() if line.startswith("Error:")] == [res.output.splitlines()[-1]]
    assert not (tmp_path / "o").exists()


def test_cli_area_too_large_is_a_usage_error(tmp_path):
    from typer.testing import CliRunner

    from egcbf.cli import app

    res = CliRunner().invoke(
        app,
        ["eval", "--controller", "nominal", "--num-agents", "8", "--area", "1e9", "--episodes", "1",
         "--out", str(tmp_path / "o"), "--no-progress"],
    )  # fmt: skip
    assert res.exit_code == 2 and "area_size must be at most" in res.output, res.output


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [
        ("seed", 1.5, "SweepConfig.seed must be an integer, got 1.5"),
        ("episodes", 2.0, "SweepConfig.episodes must be an integer, got 2.0"),
        ("train_seeds", (0, 1.5), "SweepConfig.train_seeds must be a tuple of integers"),
        ("num_agents", (8, 16.5), "SweepConfig.num_agents must be a tuple of integers"),
        ("num_agents", 8, "SweepConfig.num_agents must be a tuple of integers (e.g. (8, 16)), got 8"),
        ("methods", "egcbf+", "SweepConfig.methods must be a tuple of method names (e.g. ('egcbf+',)), got 'egcbf+'"),
        ("max_steps", 2.5, "SweepConfig.max_steps must be an integer or None, got 2.5"),
        ("area", "4", "SweepConfig.area must be a finite number, got '4'"),
    ],
)
def test_sweep_config_refuses_floats_that_would_be_truncated_and_wrong_types(field, value, words):
    """The reproduce API: a float seed or size is refused (``int()`` ran seed 1.5 as seed 1), and a string or a bare
    number where a tuple belongs is named (``methods="egcbf+"`` was read as its characters)."""
    from egcbf.reproduce import SweepConfig

    with pytest.raises(TypeError) as info:
        SweepConfig(**{field: value})
    assert words in str(info.value), str(info.value)
    SweepConfig(seed=3, train_seeds=[0, 1], num_agents=[8])  # integers, in a list or a tuple: fine


def test_evaluate_names_a_controller_factory_that_is_not_callable():
    with pytest.raises(TypeError, match=r"^evaluate: make_controller must be a callable EnvConfig -> controller"):
        evaluate(None, [2], area_size=2.0, episodes=1, show_progress=False)
    with pytest.raises(TypeError, match=r"make_controller .* got str"):
        evaluate("nominal", [2], area_size=2.0, episodes=1, show_progress=False)


def test_train_names_an_argument_of_the_wrong_type(tmp_path):
    from egcbf.train.loop import train

    with pytest.raises(TypeError, match=r"^train\(\) argument config must be a TrainConfig, got dict"):
        train({"algo": "egcbf+"}, tmp_path)
    with pytest.raises(TypeError, match=r"^train\(\) argument out must be a run directory .*got 3"):
        train(TrainConfig.preset("egcbf+", "tiny"), 3)
    with pytest.raises(TypeError, match=r"argument out must be a run directory .*got ''"):
        train(TrainConfig.preset("egcbf+", "tiny"), "")
    assert not any(tmp_path.iterdir())  # refused before anything was written


def test_run_episodes_with_no_seeds_names_the_cause():
    from egcbf.control.controllers import NominalController
    from egcbf.evaluate.episodes import run_episodes

    with pytest.raises(ValueError, match="seeds is empty"):
        run_episodes(NominalController(), EnvConfig(num_agents=2, area_size=2.0), [])
