"""Shared fixtures of the bad-input suite: a CLI runner and one tiny trained run (seconds)."""

import pytest
from typer.testing import CliRunner

from egcbf.algo.config import TrainConfig
from egcbf.cli import app
from egcbf.train.loop import train


@pytest.fixture
def cli(monkeypatch):
    """``cli(*args)`` runs the ``egcbf`` command line in-process and returns typer's ``Result``."""
    monkeypatch.delenv("EGCBF_DEBUG", raising=False)

    def run(*args):
        return CliRunner().invoke(app, [str(a) for a in args], env={"COLUMNS": "400"})

    return run


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """A finished ``tiny`` EGCBF+ run of 4 updates (checkpoints step_000002 and step_000004, best/, logs)."""
    out = tmp_path_factory.mktemp("tiny_run")
    train(TrainConfig.preset("egcbf+", "tiny", steps=4), out, progress=False, log=lambda s: None)
    return out
