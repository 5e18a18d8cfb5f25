"""`egcbf.train.checkpoint` is the on-disk format alone: evaluating, plotting and reproducing from checkpoints never
import the trainer, and reading a checkpoint's metadata needs no network code."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

CODE = """
import sys
import egcbf.train.checkpoint as ckpt
assert "egcbf.algo.learner" not in sys.modules and "egcbf.nn" not in sys.modules, "metadata needs no networks"
assert ckpt.read_config(sys.argv[1]).algo == "egcbf+"
import egcbf.cli, egcbf.cli.demo, egcbf.cli.eval, egcbf.viz.contour, egcbf.reproduce
ctrl, cfg = ckpt.load_controller(sys.argv[1])
net, _ = egcbf.viz.contour.load_cbf(sys.argv[1])
assert "egcbf.train.loop" not in sys.modules, sorted(m for m in sys.modules if m.startswith("egcbf"))
print("OK")
"""


def test_loading_checkpoints_does_not_import_the_trainer():
    res = subprocess.run(
        [sys.executable, "-c", CODE, str(ROOT / "checkpoints" / "egcbf+")], capture_output=True, text=True, timeout=300
    )
    assert res.returncode == 0 and "OK" in res.stdout, res.stdout + res.stderr


def test_a_run_directory_loads_its_best_checkpoint_for_evaluation(tmp_path):
    """load_network / load_controller of a run: its best/ (what the docs and `egcbf eval` say), not the newest
    checkpoint (which only resuming wants)."""
    import shutil
    from pathlib import Path

    from egcbf.train.checkpoint import CHECKPOINTS_DIR, load_controller

    root = Path(__file__).resolve().parents[2] / "checkpoints"
    run = tmp_path / "run"
    shutil.copytree(root / "egcbf+", run / "best")
    shutil.copytree(root / "gcbf+", run / CHECKPOINTS_DIR / "step_000001")
    _, cfg = load_controller(run)
    assert cfg.algo == "egcbf+"
    shutil.rmtree(run / "best")
    assert load_controller(run)[1].algo == "gcbf+"
