"""The equivariance study (egcbf.study): its plan builds, its driver trains and evaluates resumably (tiny runs), and
its report turns result files into effects, intervals and verdicts (synthetic results with known answers)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from egcbf.algo.config import TrainConfig
from egcbf.cli import app
from egcbf.evaluate.bootstrap import Interval
from egcbf.reproduce import cell_key
from egcbf.reproduce.store import checkpoint_dir
from egcbf.study import ARMS, Arm, RotatedCell, Run, arm, pending_runs, train_command, train_runs, verdict, write_report
from egcbf.study.driver import evaluate_arm, evaluate_rotated, evaluate_rotated_many, sweep_config
from egcbf.study.plan import rotated_cells
from egcbf.study.report import default_quote_targets


# ---------------------------------------------------------------------------------------------------------- plan
def test_every_arm_builds_and_keeps_its_checkpoints_where_reproduce_looks():
    assert len({a.name for a in ARMS}) == len(ARMS)
    for a in ARMS:
        for run in a.all_runs():
            cfg = a.config(run.algo, run.seed)
            assert cfg.algo == run.algo and cfg.seed == run.seed and cfg.max_cpu_minutes == a.minutes
            assert cfg.max_wall_minutes is None
            assert run.checkpoint_dir("R") == checkpoint_dir(Path("R") / "checkpoints" / a.name, run.algo, run.seed)
        if a.evaluation == "table":
            cfg = sweep_config(a, "R")
            assert set(cfg.methods) == set(a.algos()) and cfg.episodes >= 20 and cfg.obstacles == 0
            assert {(c.method, c.train_seed or 0) for c in cfg.cells()} == set(a.runs)
    assert arm("crossing").config("egcbf+", 0).scene == "crossing"
    assert arm("low-data").config("gcbf+", 0).rollout_envs * 4 == TrainConfig.preset("gcbf+", "paper-cpu").rollout_envs
    assert {a.overrides.get("model", {}).get(k) for a in ARMS for k in ("edge_closest_approach",)} >= {False}
    with pytest.raises(ValueError, match="unknown arm 'x'"):
        arm("x")


def test_train_command_starts_fresh_then_resumes(tmp_path):
    a, run = arm("cpu-20"), Run("cpu-20", "egcbf+", 0)
    cmd = train_command(run, a, tmp_path)
    assert cmd[2:5] == ["egcbf", "train", "--out"] and "--resume" not in cmd and cmd[cmd.index("--seed") + 1] == "0"
    fields = json.loads((tmp_path / "cpu-20" / "egcbf+-s0.config.json").read_text())
    assert fields == {"preset": "cpu", "max_wall_minutes": None, "max_cpu_minutes": 20.0, "seed": 0}
    (tmp_path / "cpu-20" / "egcbf+-s0" / "checkpoints" / "step_00000002").mkdir(parents=True)
    assert train_command(run, a, tmp_path)[-1] == "--resume"


def test_verdict_rule():
    def iv(lo, hi):
        return Interval((lo + hi) / 2, lo, hi, 0.95, 1000, 3, 20)

    assert verdict([iv(0.01, 0.05), iv(0.002, 0.03)]) == "supported"
    assert verdict([iv(-0.01, 0.05), iv(-0.02, 0.01)]) == "not supported"
    assert verdict([iv(-0.05, -0.01), iv(-0.02, 0.01)]) == "not supported (the world-frame method is better)"
    assert verdict([iv(0.01, 0.05), iv(-0.02, 0.01)]) == "mixed"
    assert verdict([iv(0.01, 0.05), None]) == verdict([]) == "pending"


# -------------------------------------------------------------------------------------------------------- driver
def test_tiny_runs_train_resume_and_evaluate_end_to_end(tmp_path):
    """Two tiny runs train in two processes, their best/ lands in the study's checkpoint layout, a second call
    trains nothing, and the arm's reproduce cells and rotated cells are computed once."""
    tiny = Arm("tiny", "tiny", (("egcbf+", 0), ("gcbf+", 0)), 1.0, "test", table_sizes=(3,), episodes=1)
    root, runs = tmp_path / "res", tmp_path / "runs"
    done = train_runs([tiny], jobs=2, root=root, runs_dir=runs, log=lambda s: None, poll_s=0.2)
    assert sorted(r.name for r in done) == ["egcbf+-s0", "gcbf+-s0"] and not pending_runs([tiny], root)
    for r in done:
        d = r.checkpoint_dir(root)
        names = {p.name for p in d.iterdir()}
        assert names == {"config.json", "model.safetensors", "state.json", "metrics.csv", "machine.json"}
        assert json.loads((d / "machine.json").read_text())["cores"] >= 1
        assert json.loads((d / "config.json").read_text())["max_cpu_minutes"] is not None
        assert (runs / "tiny" / r.name / "study_done.json").exists()
    assert train_runs([tiny], root=root, runs_dir=runs, log=lambda s: None) == []
    evaluate_arm(tiny, root, workers=1, log=lambda s: None)
    cells = sorted((root / "cells" / "tiny").rglob("N*.json"))
    assert len(cells) == 2 and all("per_episode" in json.loads(p.read_text())["row"] for p in cells)
    small = [RotatedCell("crossing", yaw, 3, 1.5, 0, episodes=1) for yaw in (0.0, 90.0)]
    run = Run("tiny", "egcbf+", 0)
    assert evaluate_rotated(run, root, lambda s: None, small) == 2
    assert evaluate_rotated(run, root, lambda s: None, small) == 0  # stored with the same checkpoint: kept
    # several runs' cells at once over two worker processes: the same files as one at a time
    more = [*small, RotatedCell("uniform", 0.0, 3, 1.5, 0, episodes=1)]
    logs: list[str] = []
    assert evaluate_rotated_many([run, Run("tiny", "gcbf+", 0)], root, 2, logs.append, more) == 4
    assert len(logs) == 4 and all(line.startswith("rotated tiny/") for line in logs)
    assert evaluate_rotated_many([run, Run("tiny", "gcbf+", 0)], root, 2, logs.append, more) == 0


# -------------------------------------------------------------------------------------------------------- report
def _row(values: list[float]) -> dict:
    v = np.asarray(values)
    keys = ("safe_rate", "reach_rate", "success_rate", "cost", "reward")
    return {"safe_rate": float(v.mean()), "success_rate": float(v.mean()), "reach_rate": 1.0, "num_episodes": len(v),
            "per_episode": {k: list(map(float, v)) for k in keys}}  # fmt: skip


def _write_cells(a: Arm, root: Path, safe: dict[str, float], rng) -> None:
    cfg = sweep_config(a, root)
    for c in cfg.cells():
        rec = {"key": cell_key(cfg, c, "sha"), "row": _row(list(rng.normal(safe[c.method], 0.005, 20))), "meta": {}}
        c.path(cfg.out).parent.mkdir(parents=True, exist_ok=True)
        c.path(cfg.out).write_text(json.dumps(rec))


def _write_curve(run: Run, a: Arm, root: Path, level: float) -> None:
    d = run.checkpoint_dir(root)
    d.mkdir(parents=True)
    a.config(run.algo, run.seed).to_json(d / "config.json")
    lines = ["step,wall_s,safe_rate,reach_rate,success_rate"]
    lines += [f"{s},{6 * s},{level},{level},{min(1.0, level * s / 50)}" for s in range(0, 110, 10)]
    (d / "metrics.csv").write_text("\n".join(lines) + "\n")


def test_report_reads_effects_and_verdicts_from_result_files(tmp_path):
    """Synthetic results with known answers: EGCBF+ 99 % against GCBF+ 90 % safe at every N (claim 1 supported),
    identical validation curves and low-data safety (claim 2 not supported), EGCBF+ constant under rotation while
    GCBF+ drops (claim 3 supported). The report says so, draws its figures, and keeps hand-written text on a
    rewrite."""
    rng = np.random.default_rng(0)
    root, report = tmp_path / "res", tmp_path / "docs" / "equivariance.md"
    safe = {"egcbf+": 0.99, "gcbf+": 0.90, "egcbf": 0.95, "gcbf": 0.95}
    for name in ("paper-cpu", "paper-cpu-mlp", "low-data"):
        a = arm(name)
        _write_cells(a, root, safe if name != "low-data" else dict.fromkeys(safe, 0.95), rng)
        for run in a.all_runs():
            _write_curve(run, a, root, 0.9)
    for run in arm("crossing").all_runs():
        same = list(rng.normal(0.95, 0.01, 50).clip(0, 1))  # an equivariant policy: the same episodes, rotated
        for cell in rotated_cells():
            level = 0.95 if cell.yaw == 0 else 0.6
            values = same if run.algo == "egcbf+" else list(rng.normal(level, 0.01, 50).clip(0, 1))
            path = cell.path(run, root)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps({"key": {}, "row": _row(values)}))
    # the heads ablation: the full recipe has no gap, switching the soft-min CBF head off opens one
    for name in ("cpu-20", "no-closest", "mlp-cbf", "mlp-policy"):
        gap = {"egcbf+": 0.95, "gcbf+": 0.80 if name == "mlp-cbf" else 0.95}
        _write_cells(arm(name), root, dict(gap), rng)
    quoting, plain = tmp_path / "docs" / "reproduction.md", tmp_path / "README.md"
    quoting.parent.mkdir(parents=True, exist_ok=True)
    quoting.write_text("Before.\n\n<!-- equivariance-verdicts:begin -->\nold\n<!-- equivariance-verdicts:end -->\n")
    plain.write_text("No markers here.\n")
    path, verdicts = write_report(report, root, quote_in=default_quote_targets(report))
    assert verdicts == {"generalization": "supported", "convergence": "not supported", "transfer": "supported"}
    quoted = quoting.read_text()
    assert quoted.startswith("Before.") and "old" not in quoted and "[equivariance.md](equivariance.md)" in quoted
    assert "zero-shot generalization" in quoted and "**supported** (+9." in quoted and "**not supported**" in quoted
    assert plain.read_text() == "No markers here.\n"
    assert "**Reading: supported for mlp-cbf: switching it off opens a gap in EGCBF+'s favour**" in path.read_text()
    assert "GCBF+ loses up to 3" in path.read_text()  # 95 % -> 60 %: 35 points, beyond the interval
    text = path.read_text()
    assert "- **generalization**: supported" in text and "paper-cpu, N = 512: EGCBF+ - GCBF+ = +9." in text
    for fig in ("zero_shot", "curves", "rotated"):
        assert (tmp_path / "docs" / "figures" / f"equivariance_{fig}.png").stat().st_size > 0
        assert f"figures/equivariance_{fig}.png" in text
    path.write_text(text + "\nA hand-written reading.\n")
    write_report(report, root)
    assert "A hand-written reading." in report.read_text() and report.read_text().count("<!-- rotated:begin -->") == 1


def test_study_command_plans_and_reports(tmp_path):
    res = CliRunner().invoke(app, ["study", "--plan", "--arms", "crossing", "--root", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert "crossing: transfer" in res.output and "4 run(s) to train" in res.output
    res = CliRunner().invoke(app, ["study", "--arms", "nope", "--plan"])
    assert res.exit_code == 2 and "--arms: unknown arm 'nope'" in res.output
    out = tmp_path / "eq.md"
    res = CliRunner().invoke(app, ["study", "--report-only", "--root", str(tmp_path / "r"), "--report", str(out)])
    assert res.exit_code == 0, res.output
    assert "generalization: pending" in res.output and out.exists()
