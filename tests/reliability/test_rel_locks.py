"""One writer per results directory: two commands started at once into one --out never both report success with
one's results lost; and --out values that would write somewhere unintended are refused."""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from egcbf.cli import app
from egcbf.io.locks import LOCK_NAME, DirLock, DirLockedError

EGCBF = [sys.executable, "-m", "egcbf"]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def _hold(directory: Path, ready: Path, what: str = "egcbf eval") -> subprocess.Popen:
    """A second process holding ``directory``'s lock until killed."""
    code = (
        "import pathlib, time\nfrom egcbf.io.locks import DirLock\n"
        f"with DirLock({str(directory)!r}, {what!r}):\n    pathlib.Path({str(ready)!r}).touch()\n    time.sleep(120)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], env=ENV)
    deadline = time.time() + 30
    while not ready.exists() and time.time() < deadline:
        time.sleep(0.05)
    assert ready.exists(), "the holder did not start"
    return proc


def test_lock_is_exclusive_between_processes_and_names_the_holder(tmp_path):
    holder = _hold(tmp_path / "out", tmp_path / "ready")
    try:
        with pytest.raises(DirLockedError, match=rf"being written by egcbf eval \(pid {holder.pid}\)"):
            with DirLock(tmp_path / "out", "test"):
                pass
    finally:
        holder.kill()
        holder.wait()
    with DirLock(tmp_path / "out", "test"):  # the kernel released it with the process (kill -9)
        pass


def test_lock_is_reentrant_within_a_process(tmp_path):
    with DirLock(tmp_path, "outer"), DirLock(tmp_path, "inner"):
        pass
    assert (tmp_path / LOCK_NAME).exists()


def test_a_directory_the_lock_created_and_no_one_used_goes_with_it(tmp_path):
    """A command refused for bad settings after taking the lock leaves no empty directory behind; a directory that
    existed before, or that received files, stays."""
    with pytest.raises(ValueError), DirLock(tmp_path / "new" / "out", "test"):
        raise ValueError("bad settings")
    assert list(tmp_path.iterdir()) == []  # neither out nor the parent it needed
    with DirLock(tmp_path / "used", "test"):
        (tmp_path / "used" / "metrics.json").write_text("{}")
    assert (tmp_path / "used" / "metrics.json").exists()
    (tmp_path / "old").mkdir()
    with DirLock(tmp_path / "old", "test"):
        pass
    assert (tmp_path / "old").is_dir()


def _eval_cmd(out: Path) -> list[str]:
    return [*EGCBF, "eval", "--controller", "nominal", "--num-agents", "4", "--area", "2", "--episodes", "1",
            "--max-steps", "30", "--out", str(out), "--no-progress", "--threads", "1"]  # fmt: skip


def test_two_evals_started_together_into_one_out(tmp_path):
    """Both start at the same moment: exactly one writes its results, the other stops with a clear error."""
    out = tmp_path / "out"
    procs = [subprocess.Popen(_eval_cmd(out), env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]  # fmt: skip
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    codes = sorted(rc for rc, _ in results)
    assert codes == [0, 2], results
    loser = next(err for rc, err in results if rc == 2)
    assert ("being written by egcbf eval" in loser) or ("already holds results" in loser), loser
    assert (out / "metrics.json").exists()


def test_eval_into_a_directory_held_by_another_process_is_refused(tmp_path):
    out = tmp_path / "out"
    holder = _hold(out, tmp_path / "ready", "egcbf demo")
    try:
        res = subprocess.run(_eval_cmd(out), env=ENV, capture_output=True, text=True, timeout=300)
    finally:
        holder.kill()
        holder.wait()
    assert res.returncode == 2 and f"being written by egcbf demo (pid {holder.pid})" in res.stderr, res.stderr
    assert not (out / "metrics.json").exists()


def _invoke(args):
    return CliRunner().invoke(app, args)


@pytest.mark.parametrize("value", ["", "."])
def test_empty_or_current_directory_out_is_refused(value, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    res = _invoke(["eval", "--controller", "nominal", "--num-agents", "4", "--episodes", "1", "--out", value])
    assert res.exit_code == 2 and "is empty or '.'" in res.output, res.output
    assert not list(tmp_path.iterdir())


def test_eval_into_a_training_run_directory_is_refused(tiny_run, tmp_path):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    before = sorted(p.name for p in run.iterdir())
    res = _invoke(["eval", "--controller", "nominal", "--num-agents", "4", "--episodes", "1", "--out", str(run)])
    assert res.exit_code == 2 and "is a training run or checkpoint directory" in res.output, res.output
    assert sorted(p.name for p in run.iterdir()) == before
    res = _invoke(["eval", "--controller", "nominal", "--num-agents", "4", "--episodes", "1",
                   "--out", str(run / "best")])  # fmt: skip
    assert res.exit_code == 2 and "training run or checkpoint directory" in res.output, res.output


def test_dangling_symlink_out_is_named(tmp_path):
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "missing" / "target")
    res = _invoke(["eval", "--controller", "nominal", "--num-agents", "4", "--episodes", "1", "--out", str(link)])
    assert res.exit_code == 2 and "symbolic link" in res.output and "does not exist" in res.output, res.output


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_resume_on_a_read_only_run_is_a_clear_error(tiny_run, tmp_path):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    run.chmod(0o555)
    try:
        res = _invoke(["train", "--out", str(run), "--resume", "--steps", "4", "--no-progress"])
    finally:
        run.chmod(0o755)
    assert res.exit_code == 2 and "is not writable" in res.output, res.output


def _read_only_mount_works() -> bool:
    """Whether this process may bind-mount a folder read-only in a private mount namespace (root, ``unshare``)."""
    import shutil as sh
    import tempfile

    if os.geteuid() != 0 or sh.which("unshare") is None or sh.which("mount") is None:
        return False
    with tempfile.TemporaryDirectory() as d:
        script = f"mount --bind {d} {d} && mount -o remount,bind,ro {d} {d} && ! touch {d}/x 2>/dev/null"
        probe = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, timeout=30)
    return probe.returncode == 0


@pytest.mark.skipif(not _read_only_mount_works(), reason="needs root and unshare -m (a real read-only mount)")
def test_resume_on_read_only_storage_is_a_clear_error(tiny_run, tmp_path):
    """Read-only storage as root meets it (chmod does not stop root): the run folder bind-mounted read-only in a
    private mount namespace; --resume stops with one error line naming the folder, and the run is unchanged."""
    import shlex
    import shutil

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    before = sorted(str(p.relative_to(run)) for p in run.rglob("*"))
    cmd = shlex.join([*EGCBF, "train", "--out", str(run), "--resume", "--steps", "6", "--no-progress"])
    q = shlex.quote(str(run))
    script = f"mount --bind {q} {q} && mount -o remount,bind,ro {q} {q} && exec {cmd}"
    res = subprocess.run(["unshare", "-m", "sh", "-c", script], env=ENV, capture_output=True, text=True, timeout=300)
    assert res.returncode == 2, res.stderr
    errors = [line for line in res.stderr.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1 and f"--out {run} is not writable" in errors[0], res.stderr
    assert "Read-only file system" in errors[0] and "Traceback" not in res.stderr
    assert sorted(str(p.relative_to(run)) for p in run.rglob("*")) == before
