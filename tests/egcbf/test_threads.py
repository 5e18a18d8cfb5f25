"""Torch CPU threads for `egcbf eval` / `egcbf demo`: all free CPUs, one fewer per busy one, --threads wins."""

import json
import os

import pytest
import torch
from typer.testing import CliRunner

from egcbf.cli import app
from egcbf.io import threads
from egcbf.io.threads import choose_threads


@pytest.fixture
def machine(monkeypatch):
    """A fake machine: ``machine(cpus, load)``; ``load=None`` for an OS without a load average. The CPU-time
    sample is unavailable (as off Linux) unless a test sets ``threads.busy_cpus`` itself."""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(threads, "busy_cpus", lambda window=threads.BUSY_WINDOW_S: None)

    def set_machine(cpus: int, load: float | None) -> None:
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cpus)), raising=False)
        monkeypatch.setattr(os, "cpu_count", lambda: 64)  # the affinity mask, not the machine, counts
        if load is None:
            monkeypatch.delattr(os, "getloadavg", raising=False)
        else:
            monkeypatch.setattr(os, "getloadavg", lambda: (load, load, load))

    return set_machine


def test_quiet_machine_uses_every_available_cpu(machine):
    machine(2, 0.1)
    n, reason = choose_threads(None)
    assert n == 2
    assert reason == "2 CPUs available, load 0.1"


@pytest.mark.parametrize(
    "cpus, load, expected",
    [(2, 1.0, 1), (2, 1.4, 1), (8, 3.0, 5), (8, 2.6, 5), (2, 2.2, 1), (2, 7.0, 1), (1, 0.9, 1), (4, 40.0, 1)],
)
def test_loaded_machine_leaves_the_busy_cpus_alone_but_keeps_one_thread(machine, cpus, load, expected):
    machine(cpus, load)
    n, reason = choose_threads()
    assert n == expected and 1 <= n <= cpus
    assert f"{cpus} CPUs available" in reason and f"load {load:.1f}" in reason


def test_without_affinity_or_load_average_uses_cpu_count(machine, monkeypatch):
    machine(2, None)
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 3)
    assert threads.available_cpus() == 3 and threads.load_average() is None
    assert choose_threads(None) == (3, "3 CPUs available, load unknown")
    monkeypatch.setattr(os, "cpu_count", lambda: None)  # unknown: still one thread
    assert choose_threads(None)[0] == 1


def test_requested_overrides_everything(machine, monkeypatch):
    machine(2, 5.0)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert choose_threads(4) == (4, "--threads 4")
    assert choose_threads(1) == (1, "--threads 1")


@pytest.mark.parametrize("bad", [0, -1, 1.5, "2", True])
def test_invalid_request_names_the_option(bad):
    with pytest.raises(ValueError, match="--threads"):
        choose_threads(bad)


def test_omp_num_threads_is_respected_when_nothing_is_requested(machine, monkeypatch):
    machine(2, 0.0)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert choose_threads(None) == (3, "OMP_NUM_THREADS=3")
    for unusable in ("0", "", "x", "4,2"):  # not a count of threads: the automatic policy decides
        monkeypatch.setenv("OMP_NUM_THREADS", unusable)
        assert choose_threads(None) == (2, "2 CPUs available, load 0.0")


@pytest.mark.parametrize("command", ["eval", "demo"])
@pytest.mark.parametrize("value", ["0", "-2"])
def test_cli_rejects_bad_threads_as_a_usage_error(tmp_path, command, value):
    args = [command, "--threads", value, "--out", str(tmp_path / "o"), "--no-progress"]
    if command == "demo":
        args += ["--method", "nominal"]  # a controller: no checkpoint needed
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2, res.output
    assert "--threads" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "o").exists()  # rejected before any work


def test_eval_says_and_records_its_threads_and_restores_torchs(tmp_path):
    before = torch.get_num_threads()
    out = tmp_path / "ev"
    args = ["eval", "--num-agents", "2", "--area", "1.5", "--episodes", "1", "--max-steps", "3", "--out", str(out)]
    res = CliRunner().invoke(app, [*args, "--no-progress", "--threads", "1"])
    assert res.exit_code == 0, res.output
    assert "threads: 1 (--threads 1)" in res.output
    run = json.loads((out / "run.json").read_text())
    assert run["threads"] == 1 and run["threads_reason"] == "--threads 1" and run["machine"]["threads"] == 1
    assert torch.get_num_threads() == before


def test_demo_chooses_threads_automatically_and_records_them(tmp_path, monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    expected, _ = choose_threads(None)  # the load may drift before the demo chooses: allow one either way
    before = torch.get_num_threads()
    out = tmp_path / "demo"
    small = ["--num-agents", "2", "--area", "1.5", "--obstacles", "0", "--episodes", "1", "--max-steps", "3"]
    res = CliRunner().invoke(app, ["demo", "--method", "nominal", "--out", str(out), "--no-progress", *small])
    assert res.exit_code == 0, res.output
    assert res.output.count("threads: ") == 1 and "CPUs available" in res.output
    summary = json.loads((out / "demo.json").read_text())
    run = json.loads((out / "nominal" / "run.json").read_text())
    assert 1 <= summary["threads"] == run["threads"] == summary["machine"]["threads"] <= threads.available_cpus()
    assert "CPUs available" in summary["threads_reason"] and abs(summary["threads"] - expected) <= 1
    assert torch.get_num_threads() == before


@pytest.mark.parametrize("cpus, busy, expected", [(2, 0.05, 2), (2, 0.4, 2), (2, 0.9, 1), (2, 1.7, 1), (8, 2.6, 5)])
def test_sampled_busy_cpus_take_precedence_over_the_load_average(machine, monkeypatch, cpus, busy, expected):
    """A just-finished job still raises the 1-minute load average; the short CPU-time sample does not see it."""
    machine(cpus, 1.0)
    monkeypatch.setattr(threads, "busy_cpus", lambda window=threads.BUSY_WINDOW_S: busy)
    assert choose_threads() == (expected, f"{cpus} CPUs available, {busy:.1f} busy")


@pytest.mark.skipif(not os.path.exists("/proc/stat") or not hasattr(os, "sched_getaffinity"), reason="Linux only")
def test_busy_cpus_measures_this_machine():
    busy = threads.busy_cpus(window=0.05)
    assert busy is not None and 0.0 <= busy <= len(os.sched_getaffinity(0)) + 1e-9


def test_busy_cpus_sees_a_busy_process():
    """One CPU-bound child on this process's CPUs shows as (about) one busy CPU."""
    if not os.path.exists("/proc/stat") or not hasattr(os, "sched_getaffinity"):
        pytest.skip("Linux only")
    import subprocess
    import sys
    import time

    child = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.3)
        busy = threads.busy_cpus(window=0.3)
    finally:
        child.kill()
        child.wait()
    assert busy is not None and busy >= 0.7
