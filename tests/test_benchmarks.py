"""The benchmark script keeps working: a quick smoke run, rendered to a temporary file (docs/ is not touched)."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_benchmark_quick_runs(tmp_path):
    out = tmp_path / "benchmarks.md"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "run.py"), "--quick", "--output", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert proc.returncode == 0, f"benchmarks/run.py --quick exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    assert "wrapped/raw ratio" in proc.stdout
    text = out.read_text()  # the markdown section is rendered (to a temporary file, not docs/)
    assert "<!-- groupcanon:begin -->" in text and "<!-- groupcanon:end -->" in text
    assert "| N | E | pass |" in text and "roma Rigid" in text


def test_filter_cost_benchmark_quick_runs():
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "filter_cost.py"), "--sizes", "16", "--steps", "4", "--stride",
         "2", "--no-write"],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, f"filter_cost.py exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    assert "| 16 |" in proc.stdout and "dcbf ms (x policy)" in proc.stdout


def test_deployment_and_gcbfplus_benchmarks_quick_run():
    """benchmarks/agent_latency.py (one agent's step: PyTorch, TorchScript, onnxruntime) and
    benchmarks/gcbfplus_speed.py (our step against the GCBF+ reference's) in a smoke run, docs untouched."""
    import pytest

    pytest.importorskip("onnxruntime")
    for args, expect in (
        (["agent_latency.py", "--repeats", "1", "--neighbours", "4", "--hits", "4", "--no-write"], "onnxruntime |"),
        (["gcbfplus_speed.py", "--steps", "1", "--warmup", "1", "--repeats", "1", "--no-write"], "Smallest speed-up"),
    ):
        proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / args[0]), *args[1:]], capture_output=True,
                              text=True, timeout=600, cwd=ROOT)  # fmt: skip
        assert proc.returncode == 0, f"{args[0]} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
        assert expect in proc.stdout


def test_step_floor_benchmark_quick_run():
    """benchmarks/step_floor.py (the arithmetic floor of the N = 512 step, issue 28) in a smoke run, docs untouched:
    both shipped policies' FLOPs and a floor above zero."""
    args = ["--repeats", "1", "--threads", "1", "--steps", "2", "--every", "1", "--no-write"]
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "step_floor.py"), *args], capture_output=True,
                          text=True, timeout=300, cwd=ROOT)  # fmt: skip
    assert proc.returncode == 0, f"step_floor.py exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    rows = [line for line in proc.stdout.splitlines() if line.startswith(("| egcbf+ |", "| gcbf+ |"))]
    assert len(rows) == 2 and all(float(r.split("|")[4]) > 0 for r in rows)


def test_policy_variants_benchmark_quick_run():
    """benchmarks/policy_variants.py (restructured policy forwards, issue 28) in a smoke run, docs untouched: every
    variant runs and agrees with the shipped forward (the script exits non-zero otherwise)."""
    args = ["--steps", "1", "--repeats", "1", "--rounds", "1", "--threads", "1", "--no-write"]
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "policy_variants.py"), *args], capture_output=True,
                          text=True, timeout=300, cwd=ROOT)  # fmt: skip
    assert proc.returncode == 0, f"policy_variants.py exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    assert "| eager PyTorch (shipped) |" in proc.stdout and "receivers in two blocks" in proc.stdout


def test_marl_interface_benchmark_quick_run():
    """benchmarks/marl_env_speed.py (agent-steps per second through SwarmEnv, SwarmTask, TorchRL, PettingZoo) in a
    smoke run, docs untouched: every path has a cell, the baseline's ratio is 1, and SwarmTask's step is split into
    its parts."""
    import pytest

    pytest.importorskip("torchrl")
    pytest.importorskip("pettingzoo")
    quick = ["--rounds", "2", "--steps", "1", "--warmup", "1", "--no-write"]
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "marl_env_speed.py"), *quick],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)  # fmt: skip
    assert proc.returncode == 0, f"marl_env_speed.py exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    lines = proc.stdout.splitlines()
    rows = [line for line in lines if line.startswith("| 8 x 512 |") or line.startswith("| 1 x")]
    speed, parts = rows[:3], rows[3:]
    assert len(rows) == 6 and all("(1.00x)" in r for r in speed)
    assert speed[-1].count("agent") == 0 and speed[-1].count("x)") == 5  # the one-scene row has all five paths
    # where SwarmTask's step goes: four parts in ms and the observation / simulator ratio, all positive
    assert all(len(r.strip("|").split("|")) == 8 and float(r.strip("|").split("|")[-1]) > 0 for r in parts)


def test_the_sweep_account_covers_every_cell_and_is_in_the_docs():
    """benchmarks/sweep_cpu_hours.py counts every cell of the reproduction's plan once (computed or pending), and
    docs/benchmarks.md holds what it writes from the committed cells (`make report` regenerates it)."""
    import importlib.util

    from egcbf.io.report import replace_block
    from egcbf.reproduce.store import load_cells

    spec = importlib.util.spec_from_file_location("sweep_cpu_hours", ROOT / "benchmarks" / "sweep_cpu_hours.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    cfg = mod.SweepConfig(out=ROOT / "docs" / "results" / "reproduction", checkpoints=ROOT / "checkpoints")
    _, total = mod.account(cfg)
    assert total["computed"] == len(load_cells(cfg)) and total["computed"] + total["pending"] == len(cfg.cells())
    text = (ROOT / "docs" / "benchmarks.md").read_text()
    assert replace_block(text, "sweep-cpu-hours", mod.markdown(cfg)) == text
