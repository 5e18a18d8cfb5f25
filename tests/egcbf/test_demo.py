"""`egcbf demo`: the learned method beside its baseline on the same seeds (tiny checkpoints, short episodes)."""

import json

import pytest
from typer.testing import CliRunner

from egcbf.cli import app
from egcbf.config import TrainConfig
from egcbf.train import train

SMALL = ["--num-agents", "3", "--area", "1.5", "--obstacles", "1", "--episodes", "1", "--max-steps", "8"]


def _invoke(args):
    return CliRunner().invoke(app, ["demo", "--no-progress", *args], env={"COLUMNS": "400"})


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    root = tmp_path_factory.mktemp("checkpoints")
    for algo in ("egcbf+", "gcbf+"):  # run directories: the demo takes their newest checkpoint
        train(TrainConfig.preset(algo, "tiny", steps=1), root / algo, progress=False, log=lambda s: None)
    return root


def test_demo_compares_the_learned_policy_with_its_baseline(checkpoints, tmp_path):
    out = tmp_path / "demo"
    res = _invoke(["--checkpoints", str(checkpoints), "--out", str(out), *SMALL])
    assert res.exit_code == 0, res.output
    for name in ("egcbf+", "gcbf+"):
        rows = json.loads((out / name / "metrics.json").read_text())
        assert [r["num_agents"] for r in rows] == [3] and rows[0]["num_episodes"] == 1
    assert (out / "egcbf+" / "egcbf+_N3.gif").read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    assert (out / "egcbf+" / "egcbf+_N3_topdown.png").stat().st_size > 0
    assert not list((out / "gcbf+").glob("*.gif"))  # the baseline is not rendered
    summary = json.loads((out / "demo.json").read_text())
    assert summary["method"] == "egcbf+" and summary["baseline"] == "gcbf+"
    assert set(summary["metrics"]) == {"egcbf+", "gcbf+"} and summary["num_agents"] == 3
    assert res.output.count("Safe%") == 2 and "egcbf+ vs gcbf+ on the same 1 episodes" in res.output


def test_demo_names_a_missing_checkpoint_and_how_to_train_it(tmp_path):
    missing = tmp_path / "nothing-here"
    res = _invoke(["--checkpoints", str(missing), "--out", str(tmp_path / "o"), *SMALL])
    assert res.exit_code != 0
    assert str(missing / "egcbf+") in res.output and "egcbf train --algo egcbf+" in res.output
    assert not (tmp_path / "o").exists()  # failed before any work


def test_demo_with_a_missing_baseline_fails_before_evaluating(checkpoints, tmp_path):
    res = _invoke(["--checkpoints", str(checkpoints), "--baseline", "gcbf", "--out", str(tmp_path / "o"), *SMALL])
    assert res.exit_code != 0 and "egcbf train --algo gcbf " in res.output
    assert not (tmp_path / "o").exists()


def test_demo_runs_a_hand_crafted_controller_without_checkpoints(tmp_path):
    out = tmp_path / "demo"
    res = _invoke(["--method", "ccbf", "--checkpoints", str(tmp_path / "none"), "--out", str(out), *SMALL])
    assert res.exit_code == 0, res.output
    assert (out / "ccbf" / "metrics.json").exists() and (out / "ccbf" / "ccbf_N3.gif").exists()
    assert json.loads((out / "demo.json").read_text())["baseline"] is None


def test_demo_rejects_an_unknown_method(tmp_path):
    res = _invoke(["--method", "nope", "--out", str(tmp_path / "o"), *SMALL])
    assert res.exit_code != 0 and "unknown method" in res.output
