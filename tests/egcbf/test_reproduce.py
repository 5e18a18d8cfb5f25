"""`egcbf reproduce`: cells, resuming, baseline import, backends, report (tiny swarms, short episodes)."""

import json
import pickle
import shutil
import sys
import types

import pytest
from typer.testing import CliRunner

from egcbf import reproduce as rp
from egcbf.cli import app
from egcbf.config import TrainConfig
from egcbf.control.controllers import make_controller
from egcbf.evaluate import evaluate
from egcbf.reproduce import Cell, SweepConfig
from egcbf.train import load_controller, train

TIMING = ("step_ms_median", "qp_ms_median")


def _metrics(row: dict) -> dict:
    return {k: v for k, v in row.items() if k not in TIMING}


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """``CHECKPOINTS/egcbf+``: the best policy of a one-update tiny run, with its metrics.csv."""
    root = tmp_path_factory.mktemp("repro")
    run = root / "run"
    train(TrainConfig.preset("egcbf+", "tiny", steps=1), run, progress=False, log=lambda s: None)
    ckpts = root / "checkpoints"
    shutil.copytree(run / "best", ckpts / "egcbf+")
    shutil.copy(run / "metrics.csv", ckpts / "egcbf+" / "metrics.csv")
    return ckpts


def _cfg(checkpoints, out, **kw) -> SweepConfig:
    base = dict(
        methods=("egcbf+", "dcbf"),
        num_agents=(2, 3),
        area=1.5,
        obstacles=1,
        obstacle_methods=("egcbf+",),
        episodes=2,
        seed=3,
        max_steps=5,
        checkpoints=checkpoints,
        out=out,
        baselines=None,
        workers=1,
    )
    base.update(kw)
    return SweepConfig(**base)


@pytest.fixture(scope="module")
def first(checkpoints, tmp_path_factory):
    """A finished sweep (workers=1): its config and records."""
    cfg = _cfg(checkpoints, tmp_path_factory.mktemp("out"))
    return cfg, rp.sweep(cfg, command="egcbf reproduce (test)", progress=False, log=lambda s: None)


def test_cells_are_written_and_equal_evaluate(first, checkpoints):
    cfg, records = first
    expected = [Cell(m, k, n) for k, ms in ((0, ("dcbf", "egcbf+")), (1, ("egcbf+",))) for m in ms for n in (2, 3)]
    assert set(records) == set(expected) and set(cfg.cells()) == set(expected)
    for cell in expected:
        stored = json.loads(cell.path(cfg.out).read_text())
        assert stored["key"]["episodes"] == 2 and stored["meta"]["wall_s"] >= 0 and stored["meta"]["machine"]["cpu"]
        assert (stored["key"]["checkpoint_sha256"] is None) == (cell.method == "dcbf")
    ctrl, tcfg = load_controller(checkpoints / "egcbf+")
    for cell in expected:  # what `egcbf eval` computes for the same N
        learned = cell.method == "egcbf+"
        rows, _ = evaluate(
            (lambda c: ctrl) if learned else (lambda c: make_controller("dcbf")),
            [cell.num_agents],
            area_size=1.5,
            num_obstacles=cell.obstacles,
            episodes=2,
            seed=3,
            max_steps=5,
            show_progress=False,
            env_overrides=dict(tcfg.env_overrides) if learned else None,
        )
        assert _metrics(records[cell]["row"]) == _metrics(rows[0])


def test_resume_recomputes_nothing_then_only_changed_cells(first, monkeypatch):
    cfg, records = first

    def boom(task):
        raise AssertionError(f"recomputed {task.cell}")

    monkeypatch.setattr(rp, "run_cell", boom)
    again = rp.sweep(cfg, progress=False, log=lambda s: None)
    assert again == records
    log = json.loads((cfg.out / "sweep.json").read_text())
    assert log[-1]["reused"] == len(records) and log[-1]["computed"] == 0

    calls = []

    def fake(task):
        calls.append(task.cell)
        return {"row": records[task.cell]["row"], "wall_s": 0.0, "machine": {}}

    monkeypatch.setattr(rp, "run_cell", fake)
    other = SweepConfig(**{**cfg.__dict__, "episodes": 3, "out": cfg.out.parent / "other"})
    shutil.copytree(cfg.out, other.out)
    rp.sweep(other, progress=False, log=lambda s: None)
    assert sorted(calls) == sorted(cfg.cells())
    assert calls[0].num_agents == 3  # largest N first


def test_baseline_import(checkpoints, tmp_path):
    base = tmp_path / "baselines" / "dcbf"
    base.mkdir(parents=True)
    row = {"num_agents": 2, "safe_rate": 0.5, "reach_rate": 0.25, "success_rate": 0.25, "cost": 1.0}
    row.update(cost_min=0.0, cost_max=2.0, reward=-1.0, step_ms_median=1.0)
    (base / "metrics.json").write_text(json.dumps([row]))
    run = {"command": "egcbf eval --controller dcbf --num-agents 2 --area 1.5 --obstacles 0 --episodes 2 --seed 3"}
    run.update(controller="dcbf", checkpoint=None, area=1.5, obstacles=0, episodes=2, seed=3, wall_s=1.0)
    (base / "run.json").write_text(json.dumps(run))
    cfg = _cfg(checkpoints, tmp_path / "out", methods=("dcbf",), max_steps=None, baselines=tmp_path / "baselines")
    cell = Cell("dcbf", 0, 2)
    key = rp.cell_key(cfg, cell, None)
    got = rp.import_baseline(cfg.baselines, cell, key)
    assert got is not None and got[0] == row and got[1]["imported_from"] == str(base)
    assert rp.import_baseline(cfg.baselines, Cell("dcbf", 0, 3), key | {"num_agents": 3}) is None  # no such row
    assert rp.import_baseline(cfg.baselines, cell, key | {"episodes": 5}) is None
    assert rp.import_baseline(cfg.baselines, cell, key | {"max_steps": 5}) is None
    (base / "run.json").write_text(json.dumps(run | {"command": run["command"] + " --max-steps 9"}))
    assert rp.import_baseline(cfg.baselines, cell, key) is None


def test_report_sections_paper_numbers_and_figures(first, tmp_path, monkeypatch):
    cfg, records = first
    contour = pytest.importorskip("egcbf.contour")
    calls = []

    def fake_contour(checkpoints, out_png):  # the real figure takes ~10 s; its own tests cover it
        calls.append(checkpoints)
        out_png.parent.mkdir(parents=True, exist_ok=True)
        out_png.write_bytes(b"png")
        return {label: 0.0 for label in checkpoints}

    monkeypatch.setattr(contour, "cbf_contour_figure", fake_contour)
    report = tmp_path / "docs" / "reproduction.md"
    wide = SweepConfig(**{**cfg.__dict__, "methods": rp.METHODS, "num_agents": (2, 3, 16, 512)})
    rp.write_report(wide, records, report)  # cells not computed yet show as pending beside the paper's numbers
    text = report.read_text()
    assert "pending" in text
    for name in ("table", "scalability", "convergence", "contour", "provenance"):
        assert f"<!-- {name}:begin -->" in text and f"<!-- {name}:end -->" in text
    for paper in ("-505.8", "89.5", "0.51 (0.23/0.73)", "98.125"):  # Table I: GCBF, EGCBF+ at 512, dCBF at 16
        assert paper in text
    assert "egcbf reproduce (test)" in text and "sha256" in text
    assert (tmp_path / "docs" / "figures" / "reproduction_scalability.png").stat().st_size > 0
    assert (tmp_path / "docs" / "figures" / "reproduction_convergence.png").stat().st_size > 0
    assert calls == [{"EGCBF+": cfg.checkpoints / "egcbf+"}] and "figures/reproduction_contour.png" in text
    report.write_text(text + "\nhand-written note\n")
    rp.write_report(cfg, rp.load_cells(cfg), report)  # --report-only
    assert "hand-written note" in report.read_text()
    assert report.read_text().count("<!-- table:begin -->") == 1


def test_parallel_backends_match_serial(first, monkeypatch):
    cfg, records = first
    sub = dict(methods=("egcbf+",), obstacles=0)
    serial = {c: r["row"] for c, r in records.items() if c.method == "egcbf+" and c.obstacles == 0}
    pooled = rp.sweep(SweepConfig(**{**cfg.__dict__, **sub, "workers": 2, "out": cfg.out.parent / "pool"}),
                      progress=False, log=lambda s: None)  # fmt: skip
    assert {c: _metrics(r["row"]) for c, r in pooled.items()} == {c: _metrics(r) for c, r in serial.items()}
    assert all(r["meta"]["machine"]["threads"] == 1 for r in pooled.values())

    fake = _fake_ray()
    monkeypatch.setitem(sys.modules, "ray", fake)
    ray_cfg = SweepConfig(**{**cfg.__dict__, **sub, "backend": "ray", "out": cfg.out.parent / "ray"})
    remote = rp.sweep(ray_cfg, progress=False, log=lambda s: None)
    assert {c: _metrics(r["row"]) for c, r in remote.items()} == {c: _metrics(r) for c, r in serial.items()}
    assert fake.initialized and fake.remote_options == {"num_cpus": 1}


def _fake_ray() -> types.ModuleType:
    """A stand-in for ``ray`` that runs each task locally after a pickle round trip (as shipping to a node)."""
    fake = types.ModuleType("ray")
    fake.initialized, fake.remote_options = False, None

    def init(**kw):
        fake.initialized = True

    def remote(**options):
        fake.remote_options = options

        def wrap(fn):
            return types.SimpleNamespace(remote=lambda *args: (fn, pickle.dumps(args)))

        return wrap

    fake.init, fake.remote, fake.is_initialized = init, remote, lambda: fake.initialized
    fake.wait = lambda refs, num_returns=1: (refs[:num_returns], refs[num_returns:])
    fake.get = lambda ref: ref[0](*pickle.loads(ref[1]))
    return fake


def test_missing_ray_and_checkpoint_errors(checkpoints, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(ImportError, match=r"pip install -e '\.\[ray\]'"):
        rp.validate(_cfg(checkpoints, tmp_path, backend="ray"))
    with pytest.raises(FileNotFoundError, match=r"egcbf train --algo gcbf\+ --out runs/gcbf\+"):
        rp.validate(_cfg(checkpoints, tmp_path, methods=("gcbf+",)))
    with pytest.raises(ValueError, match="unknown method"):
        _cfg(checkpoints, tmp_path, methods=("nope",))
    res = CliRunner().invoke(app, ["reproduce", "--methods", "gcbf", "--checkpoints", str(tmp_path / "none")])
    assert res.exit_code != 0 and "egcbf train --algo gcbf" in res.output
    res = CliRunner().invoke(app, ["reproduce", "--methods", "dcbf", "--backend", "ray"])
    assert res.exit_code != 0 and "pip install" in res.output


def test_reproduce_command(first, tmp_path):
    cfg, records = first
    report = tmp_path / "reproduction.md"
    args = ["reproduce", "--methods", "egcbf+,dcbf", "--num-agents", "2,3", "--area", "1.5", "--obstacles", "1"]
    args += ["--obstacle-methods", "egcbf+", "--episodes", "2", "--seed", "3", "--max-steps", "5", "--no-progress"]
    args += ["--checkpoints", str(cfg.checkpoints), "--out", str(cfg.out), "--report", str(report)]
    res = CliRunner().invoke(app, args)  # every cell exists: nothing is recomputed
    assert res.exit_code == 0, res.output
    assert f"{len(records)} of {len(records)} cells" in res.output and "EGCBF+" in report.read_text()
    res = CliRunner().invoke(app, [*args, "--report-only"])
    assert res.exit_code == 0, res.output
