"""The examples run as scripts and exit 0 (each checks its own equivariance claims and exits non-zero if one fails)."""

import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


@pytest.mark.parametrize(
    "script", ["custom_group.py", "wrap_pyg_layer.py", "new_robot.py", "onboard_robot.py", "marl_envs.py"]
)
def test_example_runs(script):
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / script)], capture_output=True, text=True, timeout=300, cwd=EXAMPLES.parent
    )
    assert proc.returncode == 0, f"{script} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    assert "OK" in proc.stdout


def test_api_reference_is_in_sync():
    """docs/api.md is generated from the docstrings: regenerate with `python docs/gen_api.py` after API changes."""
    root = Path(__file__).resolve().parents[1]
    res = subprocess.run([sys.executable, str(root / "docs" / "gen_api.py"), "--check"], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def test_the_gcbfplus_report_is_generated_from_its_cells():
    """docs/gcbfplus.md is what docs/gen_gcbfplus.py writes from the committed cells (regenerate after new cells)."""
    import importlib.util

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("gen_gcbfplus", root / "docs" / "gen_gcbfplus.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    assert (root / "docs" / "gcbfplus.md").read_text() == gen.report()


def test_a_gcbfplus_cell_of_other_weights_is_not_current(monkeypatch):
    """A learned method's cell counts only for the shipped checkpoint's weights: replacing the checkpoint makes it
    pending (docs/gen_gcbfplus.py recomputes it)."""
    import importlib.util
    import json

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("gen_gcbfplus", root / "docs" / "gen_gcbfplus.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    row = next(r for r in json.loads((gen.RESULTS / "reference.json").read_text())["rows"] if r["env"] != "CrazyFlie")
    assert gen.current("gcbf+", row) is not None
    monkeypatch.setattr(gen, "shipped_sha256", lambda method, row: "0" * 64)
    assert gen.current("gcbf+", row) is None
    assert gen.current("nominal", row) is not None  # a hand-crafted controller's cell has no checkpoint


def test_the_marl_baseline_block_is_generated_from_its_files():
    """docs/marl.md's IPPO-Lagrangian block is what docs/gen_marl.py writes from checkpoints/ippo-lag/ and the
    committed reproduction cells (regenerate after new cells or a new checkpoint)."""
    import importlib.util

    from egcbf.io.report import replace_block

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("gen_marl", root / "docs" / "gen_marl.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    text = (root / "docs" / "marl.md").read_text()
    assert replace_block(text, "marl-baseline", gen.block()) == text
    assert (root / "docs" / "figures" / "marl_training.png").exists()


def test_the_setpoint_substitution_block_is_generated_from_its_runs():
    """docs/deploy.md's setpoint-substitution block is what docs/gen_setpoint.py writes from the committed runs of
    docs/results/setpoint/ (skipped until they are committed; regenerate after new runs)."""
    import importlib.util

    from egcbf.io.report import replace_block

    root = Path(__file__).resolve().parents[1]
    tracked = subprocess.run(["git", "ls-files", "docs/results/setpoint"], cwd=root, capture_output=True, text=True)
    if tracked.returncode != 0 or "metrics.json" not in tracked.stdout:
        pytest.skip("the setpoint-substitution runs (docs/results/setpoint/) are not committed")
    spec = importlib.util.spec_from_file_location("gen_setpoint", root / "docs" / "gen_setpoint.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    text = (root / "docs" / "deploy.md").read_text()
    assert replace_block(text, gen.BLOCK, gen.block()) == text
