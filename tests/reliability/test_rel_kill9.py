"""kill -9 at a controlled point of `train`, `train --resume` and `eval`: what was finished survives, complete."""

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import egcbf
from egcbf.train.checkpoint import find_checkpoint, load_controller, load_learner

SRC = str(Path(egcbf.__file__).resolve().parents[1])
TIMEOUT = 60.0


def _start(*args) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": SRC, "OMP_NUM_THREADS": "1"}
    env.pop("EGCBF_DEBUG", None)
    code = "from egcbf.cli import main; main()"
    return subprocess.Popen(
        [sys.executable, "-c", code, *map(str, args)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )


def _kill_when(proc: subprocess.Popen, ready) -> None:
    """Poll ``ready()`` and SIGKILL ``proc`` as soon as it holds (fail if it never does within TIMEOUT)."""
    t0 = time.monotonic()
    try:
        while not ready():
            if proc.poll() is not None:
                pytest.fail(f"process ended (rc {proc.returncode}) before the kill point: {proc.stderr.read()[-500:]}")
            if time.monotonic() - t0 > TIMEOUT:
                pytest.fail("the kill point was not reached in time")
            time.sleep(0.02)
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        proc.stderr.close()


def _steps(path: Path) -> list[int]:
    with open(path, newline="") as f:
        return [int(r["step"]) for r in csv.DictReader(f)]


def _train_args(out, steps):
    return ["train", "--algo", "egcbf+", "--preset", "tiny", "--steps", steps, "--out", out, "--no-progress"]


def test_kill_during_train_keeps_a_loadable_checkpoint_and_the_logs(tmp_path):
    out = tmp_path / "run"
    proc = _start(*_train_args(out, 200))
    _kill_when(proc, lambda: (out / "checkpoints" / "step_000004").is_dir())
    ckpt = find_checkpoint(out)
    learner = load_learner(ckpt)
    assert learner.step >= 4 and ckpt.name == f"step_{learner.step:06d}"
    load_controller(out / "best")
    assert _steps(out / "metrics.csv")[:3] == [0, 2, 4]


def test_kill_during_resume_never_loses_the_history(tmp_path):
    out = tmp_path / "run"
    proc = _start(*_train_args(out, 4))
    assert proc.wait(TIMEOUT) == 0, proc.stderr.read()
    proc.stderr.close()
    before = _steps(out / "metrics.csv")
    assert before == [0, 2, 4]
    proc = _start("train", "--resume", "--steps", 200, "--out", out, "--no-progress")
    _kill_when(proc, lambda: (out / "checkpoints" / "step_000006").is_dir())
    after = _steps(out / "metrics.csv")
    assert after[:3] == before and after == sorted(after)
    scal = _steps(out / "scalars.csv")
    assert scal and scal == sorted(scal) and min(scal) == 1
    assert load_learner(out).step >= 6


def test_kill_during_eval_keeps_the_finished_sizes(tmp_path):
    out = tmp_path / "ev"
    proc = _start("eval", "--controller", "nominal", "--num-agents", "4,5,6,7,8,9,10,11", "--area", "2",
                  "--episodes", "2", "--max-steps", "20", "--out", out, "--no-progress")  # fmt: skip
    _kill_when(proc, lambda: (out / "metrics.json").exists())
    rows = json.loads((out / "metrics.json").read_text())
    run = json.loads((out / "run.json").read_text())
    assert rows and [r["num_agents"] for r in rows] == [4, 5, 6, 7, 8, 9, 10, 11][: len(rows)]
    # metrics.json is written first, run.json's list of finished sizes right after it: a kill in between leaves
    # run.json one size behind, never ahead
    sizes = [r["num_agents"] for r in rows]
    assert run["finished"] == sizes[: len(run["finished"])] and len(run["finished"]) >= len(sizes) - 1
