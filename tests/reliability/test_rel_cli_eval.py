"""`egcbf eval`: every bad input is one `Error:` line naming the flag or file, exit code 2, before any work."""

import json
import os
import sys

import pytest
from rel_helpers import TINY_EVAL, assert_usage_error


def _eval(cli, out, *args):
    return cli("eval", "--out", out, *TINY_EVAL, *args)


@pytest.mark.parametrize(
    "args, phrases",
    [
        (["--num-agents", "0"], ["--num-agents", "positive"]),
        (["--num-agents", "-3"], ["--num-agents", "positive"]),
        (["--num-agents", "a,b"], ["--num-agents", "comma-separated"]),
        (["--num-agents", ","], ["--num-agents", "positive"]),
        (["--num-agents", "4.5"], ["--num-agents", "integers"]),
        (["--num-agents", "4,8,100000"], ["--num-agents 100000", "--area"]),
        (["--area", "1", "--num-agents", "4,2000"], ["--num-agents 2000", "at most"]),
        (["--area", "0"], ["--area", "> 0"]),
        (["--area", "-1"], ["--area", "> 0"]),
        (["--area", "nan"], ["--area", "finite"]),
        (["--area", "inf"], ["--area", "finite"]),
        (["--obstacles", "-1"], ["--obstacles", ">= 0"]),
        (["--episodes", "0"], ["--episodes", ">= 1"]),
        (["--episodes", "-5"], ["--episodes", ">= 1"]),
        (["--batch", "0"], ["--batch", ">= 1"]),
        (["--batch", "-1"], ["--batch", ">= 1"]),
        (["--max-steps", "0"], ["--max-steps", ">= 1"]),
        (["--device", "foo"], ["--device", "foo"]),
        (["--device", "tpu"], ["--device", "tpu"]),
        (["--device", ""], ["--device"]),
        (["--dtype", "float16"], ["--dtype", "float16"]),
        (["--controller", "nope"], ["--controller", "nope"]),
        (["--threads", "0"], ["threads"]),
    ],
)
def test_bad_flag_is_a_usage_error(cli, tmp_path, args, phrases):
    out = tmp_path / "ev"
    assert_usage_error(_eval(cli, out, *args), *phrases)
    assert not (out / "metrics.json").exists()


def test_cuda_without_cuda_is_a_usage_error(cli, tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    assert_usage_error(_eval(cli, tmp_path / "ev", "--device", "cuda"), "--device", "cuda", "not available")


def test_controller_with_checkpoint_is_refused(cli, tmp_path, tiny_run):
    res = _eval(cli, tmp_path / "ev", "--checkpoint", tiny_run, "--controller", "ccbf")
    assert_usage_error(res, "--controller", "--checkpoint")


def test_missing_checkpoint_names_the_path(cli, tmp_path):
    missing = tmp_path / "nowhere"
    assert_usage_error(_eval(cli, tmp_path / "ev", "--checkpoint", missing), "--checkpoint", str(missing))


def test_checkpoint_that_is_a_file_names_it(cli, tmp_path):
    f = tmp_path / "weights.bin"
    f.write_bytes(b"\0" * 10)
    assert_usage_error(_eval(cli, tmp_path / "ev", "--checkpoint", f), "--checkpoint", "weights.bin")


def test_out_that_is_a_file_is_refused(cli, tmp_path):
    f = tmp_path / "results.txt"
    f.write_text("keep me")
    assert_usage_error(_eval(cli, f), "--out", "is a file")
    assert f.read_text() == "keep me"


@pytest.mark.skipif(sys.platform == "win32" or os.geteuid() == 0, reason="root may write anywhere")
def test_unwritable_out_is_refused_before_any_work(cli, tmp_path):
    parent = tmp_path / "ro"
    parent.mkdir()
    parent.chmod(0o500)
    try:
        assert_usage_error(_eval(cli, parent / "ev"), "--out", "not writable")
    finally:
        parent.chmod(0o700)


def test_a_folder_with_results_is_refused_without_overwrite(cli, tmp_path):
    out = tmp_path / "ev"
    assert _eval(cli, out).exit_code == 0
    before = (out / "metrics.json").read_text()
    assert_usage_error(_eval(cli, out, "--controller", "ccbf"), "--out", "--overwrite")
    assert (out / "metrics.json").read_text() == before


def test_overwrite_replaces_results_and_old_renders(cli, tmp_path):
    out = tmp_path / "ev"
    assert _eval(cli, out, "--num-agents", "4,5", "--render").exit_code == 0
    assert (out / "nominal_N5.gif").exists()
    res = _eval(cli, out, "--num-agents", "4", "--overwrite")
    assert res.exit_code == 0, res.output
    assert [r["num_agents"] for r in json.loads((out / "metrics.json").read_text())] == [4]
    assert not list(out.glob("*.gif"))  # no render of the old run is mixed in


def test_debug_env_raises_the_underlying_error(cli, tmp_path, monkeypatch):
    from egcbf.cli.checks import UsageError

    monkeypatch.setenv("EGCBF_DEBUG", "1")
    from typer.testing import CliRunner

    from egcbf.cli import app

    res = CliRunner().invoke(app, ["eval", "--out", str(tmp_path), *TINY_EVAL, "--episodes", "0"])
    assert isinstance(res.exception, UsageError) and "--episodes" in str(res.exception)


def test_a_failure_at_a_later_size_keeps_the_finished_rows(cli, tmp_path, monkeypatch):
    import egcbf.control.resolve as resolve  # where every controller is built

    real = resolve.make_controller

    def failing(name, robot="quadrotor", **kwargs):
        ctrl = real(name, robot, **kwargs)

        def run(state, config):
            if state.num_agents == 5:
                raise RuntimeError("boom at N=5")
            return ctrl(state, config)

        return run

    monkeypatch.setattr(resolve, "make_controller", failing)
    out = tmp_path / "ev"
    res = _eval(cli, out, "--num-agents", "4,5")
    assert isinstance(res.exception, RuntimeError)
    assert [r["num_agents"] for r in json.loads((out / "metrics.json").read_text())] == [4]
    run = json.loads((out / "run.json").read_text())
    assert run["finished"] == [4] and run["complete"] is False


def test_each_size_is_written_and_the_run_marked_complete(cli, tmp_path):
    out = tmp_path / "ev"
    res = _eval(cli, out, "--num-agents", "4,6")
    assert res.exit_code == 0, res.output
    assert [r["num_agents"] for r in json.loads((out / "metrics.json").read_text())] == [4, 6]
    run = json.loads((out / "run.json").read_text())
    assert run["finished"] == [4, 6] and run["complete"] is True
    assert not list(out.glob(".*.tmp"))


def test_a_learned_policy_that_cannot_fit_in_memory_is_refused_with_the_numbers(cli, tmp_path, tiny_run, monkeypatch):
    import egcbf.cli.checks as checks

    monkeypatch.setattr(checks, "available_memory", lambda device: 1 << 20)  # 1 MiB free
    out = tmp_path / "ev"
    res = cli("eval", "--checkpoint", tiny_run, "--num-agents", "4,64", "--area", "2", "--episodes", "1",
              "--max-steps", "3", "--out", out, "--no-progress")  # fmt: skip
    assert_usage_error(res, "--num-agents 64", "MiB", "available")
    assert not (out / "metrics.json").exists()


def test_policy_memory_estimate_grows_with_density():
    from egcbf.cli.checks import policy_memory

    sparse, _ = policy_memory(1000, 20.0, 1.0, 1, 64)
    dense, edges = policy_memory(100_000, 20.0, 1.0, 1, 64)
    assert dense > 1000 * sparse and edges > 4_000_000  # ~52 neighbours each at 12.5 agents per m^3


@pytest.mark.parametrize(
    "name, content",
    [("config.json", b"{"), ("config.json", b'{"algo": "nope"}'), ("model.safetensors", b"xx"), ("state.json", b"[")],
)
def test_corrupted_checkpoint_file_is_named(cli, tmp_path, tiny_run, name, content):
    import shutil

    ck = tmp_path / "ck"
    shutil.copytree(tiny_run / "best", ck)
    (ck / name).write_bytes(content)
    assert_usage_error(_eval(cli, tmp_path / "ev", "--checkpoint", ck), "--checkpoint", name)
    assert not (tmp_path / "ev" / "metrics.json").exists()


def test_truncated_checkpoint_weights_are_named(cli, tmp_path, tiny_run):
    import shutil

    ck = tmp_path / "ck"
    shutil.copytree(tiny_run / "best", ck)
    f = ck / "model.safetensors"
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 3])
    assert_usage_error(_eval(cli, tmp_path / "ev", "--checkpoint", ck), "model.safetensors", "truncated")


def test_eval_resume_refuses_weights_that_changed_at_the_same_path(cli, tmp_path):
    """run.json records the sha256 of the weights evaluated; --resume after they changed at the same checkpoint path
    is refused (its metrics.json would hold sizes of two different policies)."""
    import json
    import shutil
    from pathlib import Path

    ckpt = tmp_path / "ckpt"
    shutil.copytree(Path(__file__).resolve().parents[2] / "checkpoints" / "egcbf+", ckpt)
    out = tmp_path / "out"
    args = ["eval", "--checkpoint", ckpt, "--num-agents", "4,6", "--area", "2", "--episodes", "1", "--max-steps", "3",
            "--no-progress", "--out", out]  # fmt: skip
    assert cli(*args).exit_code == 0
    run = json.loads((out / "run.json").read_text())
    assert len(run["weights_sha256"]) == 64
    (out / "run.json").write_text(json.dumps({**run, "finished": [4], "complete": False}))
    rows = json.loads((out / "metrics.json").read_text())
    (out / "metrics.json").write_text(json.dumps(rows[:1]))
    shutil.rmtree(ckpt)  # another policy, whole and consistent, at the same path
    shutil.copytree(Path(__file__).resolve().parents[2] / "checkpoints" / "seeds" / "egcbf+-s1", ckpt)
    res = cli(*args, "--resume")
    assert_usage_error(res, "other weights", "--overwrite")
    assert json.loads((out / "metrics.json").read_text()) == rows[:1]


def test_a_noncooperative_fraction_that_rounds_to_no_agent_is_refused(cli, tmp_path):
    res = cli("eval", "--faults", "noncoop=0.05", "--num-agents", "8", "--episodes", "1", "--max-steps", "2",
              "--no-progress", "--out", tmp_path / "out")  # fmt: skip
    assert_usage_error(res, "noncoop=0.05", "--num-agents 8", "rounds to no non-cooperative agent", "0.0625")
    assert not (tmp_path / "out" / "run.json").exists()
    ok = cli("eval", "--faults", "noncoop=0.0625", "--num-agents", "8", "--episodes", "1", "--max-steps", "2",
             "--no-progress", "--out", tmp_path / "ok")  # fmt: skip
    assert ok.exit_code == 0, ok.output
