"""`egcbf train --tensorboard`: real TensorBoard event files (the `tensorboard` extra, installed with `dev`), and a
clear usage error when the package is missing."""

import sys

import pytest
from typer.testing import CliRunner

from egcbf.cli import app

ARGS = ["train", "--algo", "egcbf+", "--preset", "tiny", "--steps", "2", "--no-progress"]


def test_tensorboard_events_hold_the_training_scalars(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = tmp_path / "run"
    res = CliRunner().invoke(app, [*ARGS, "--out", str(out), "--tensorboard"])
    assert res.exit_code == 0, res.output
    events = EventAccumulator(str(out / "tb"))
    events.Reload()
    tags = events.Tags()["scalars"]
    assert "eval/safe_rate" in tags and len(tags) > 3
    steps = [e.step for e in events.Scalars("eval/safe_rate")]
    assert steps and steps[-1] == 2


def test_no_tensorboard_by_default(tmp_path):
    out = tmp_path / "run"
    res = CliRunner().invoke(app, [*ARGS, "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert not (out / "tb").exists() and (out / "scalars.csv").exists()


def test_missing_tensorboard_is_a_usage_error_before_any_work(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "tensorboard", None)  # `import tensorboard` -> ImportError
    out = tmp_path / "run"
    res = CliRunner().invoke(app, [*ARGS, "--out", str(out), "--tensorboard"])
    assert res.exit_code == 2 and "pip install -e '.[tensorboard]'" in res.output
    assert not out.exists()
