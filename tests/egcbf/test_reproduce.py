"""`egcbf reproduce`: cells, resuming, baseline import, backends, report (tiny swarms, short episodes)."""

import dataclasses
import json
import pickle
import shutil
import sys
import types
from pathlib import Path

import pytest
from typer.testing import CliRunner

from egcbf import reproduce as rp
from egcbf.algo.config import TrainConfig
from egcbf.cli import app
from egcbf.control.controllers import make_controller
from egcbf.evaluate.episodes import evaluate
from egcbf.io.report import number, pct
from egcbf.reproduce import Cell, SweepConfig
from egcbf.reproduce.stats import Stat
from egcbf.train.checkpoint import load_controller
from egcbf.train.loop import train

TIMING = ("step_ms_median", "qp_ms_median")


def _metrics(row: dict) -> dict:
    return {k: v for k, v in row.items() if k not in TIMING}


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """``CHECKPOINTS/egcbf+`` and ``CHECKPOINTS/seeds/egcbf+-s1``: the best policies of one-update tiny runs with
    training seeds 0 and 1, with their metrics.csv."""
    root = tmp_path_factory.mktemp("repro")
    ckpts = root / "checkpoints"
    for seed, dest in ((0, ckpts / "egcbf+"), (1, ckpts / "seeds" / "egcbf+-s1")):
        run = root / f"run{seed}"
        train(TrainConfig.preset("egcbf+", "tiny", steps=1, seed=seed), run, progress=False, log=lambda s: None)
        shutil.copytree(run / "best", dest)
        shutil.copy(run / "metrics.csv", dest / "metrics.csv")
    return ckpts


def _cfg(checkpoints, out, **kw) -> SweepConfig:
    base = dict(
        methods=("egcbf+", "dcbf"),
        num_agents=(2, 3),
        area=1.5,
        obstacles=1,
        obstacle_methods=("egcbf+",),
        episodes=2,
        train_seeds=(0,),
        scale_sizes=(),
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
    expected = [
        Cell(m, k, n, None if m == "dcbf" else 0)
        for k, ms in ((0, ("dcbf", "egcbf+")), (1, ("egcbf+",)))
        for m in ms
        for n in (2, 3)
    ]
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

    monkeypatch.setattr(rp.workers, "run_cell", boom)
    again = rp.sweep(cfg, progress=False, log=lambda s: None)
    assert again == records
    log = json.loads((cfg.out / "sweep.json").read_text())
    assert log[-1]["reused"] == len(records) and log[-1]["computed"] == 0

    calls = []

    def fake(task):
        calls.append(task.cell)
        return {"row": records[task.cell]["row"], "wall_s": 0.0, "machine": {}}

    monkeypatch.setattr(rp.workers, "run_cell", fake)
    other = dataclasses.replace(cfg, episodes=3, out=cfg.out.parent / "other")
    shutil.copytree(cfg.out, other.out)
    with pytest.raises(ValueError, match=r"made with other settings.*episodes 2 \(stored\) vs 3 \(asked\)"):
        rp.sweep(other, progress=False, log=lambda s: None)  # never overwritten unasked
    assert calls == []
    rp.sweep(other, progress=False, log=lambda s: None, recompute=True)
    assert sorted(calls) == sorted(cfg.cells())
    assert calls[0].num_agents == 3  # largest N first


def test_a_failing_cell_keeps_the_others_and_the_invocation_is_recorded(first, tmp_path, monkeypatch):
    """Every finished cell is kept when another raises; sweep.json is updated after every cell, so a killed sweep
    still counts up to its last finished cell; the status says how it ended."""
    cfg, records = first
    out = tmp_path / "stopped"
    stopped = dataclasses.replace(cfg, episodes=3, out=out)
    seen = []

    def fake(task):
        log = json.loads((out / "sweep.json").read_text())
        seen.append((log[-1]["status"], log[-1]["computed"]))
        if len(seen) == 2:
            raise RuntimeError("cell broke")
        return {"row": records[task.cell]["row"], "wall_s": 0.0, "machine": {}}

    monkeypatch.setattr(rp.workers, "run_cell", fake)
    messages = []
    with pytest.raises(rp.CellsFailed, match=r"1 cell\(s\) failed.*RuntimeError: cell broke") as failed:
        rp.sweep(stopped, progress=False, log=messages.append)
    n = len(stopped.cells())
    assert seen[:2] == [("running", 0), ("running", 1)] and len(seen) == n
    assert len(failed.value.failures) == 1 and any("FAILED" in m and "cell broke" in m for m in messages)
    assert len(rp.load_cells(stopped)) == n - 1  # the others were written
    log = json.loads((out / "sweep.json").read_text())
    assert len(log) == 1 and log[0]["status"] == "failed" and (log[0]["computed"], log[0]["failed"]) == (n - 1, 1)
    assert "code" in log[0]

    def interrupt(task):
        raise KeyboardInterrupt

    monkeypatch.setattr(rp.workers, "run_cell", interrupt)
    with pytest.raises(KeyboardInterrupt):  # the failed cell is retried, and Ctrl-C stops the sweep
        rp.sweep(stopped, progress=False, log=lambda s: None)
    log = json.loads((out / "sweep.json").read_text())
    assert log[-1]["status"] == "interrupted" and log[-1]["reused"] == n - 1
    assert "1 not recorded as finished" in rp.provenance_markdown(stopped, rp.load_cells(stopped))


def test_a_second_sweep_into_the_same_directory_is_refused(first, tmp_path, monkeypatch):
    """Another process holding the results directory (a sweep, an eval) stops the sweep before it plans."""
    import subprocess
    import sys
    import time

    cfg, _ = first
    ready = tmp_path / "ready"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import pathlib, sys, time\nfrom egcbf.io.locks import DirLock\n"
        f"with DirLock({str(cfg.out)!r}, 'egcbf reproduce'):\n"
        f"    pathlib.Path({str(ready)!r}).touch()\n    time.sleep(60)\n"
    )])  # fmt: skip
    try:
        deadline = time.time() + 30
        while not ready.exists() and time.time() < deadline:
            time.sleep(0.05)

        def planned(*args):  # planning reads (and imports baselines into) OUT: only under its lock
            raise AssertionError("the sweep planned while another process held OUT")

        with (
            monkeypatch.context() as patch,
            pytest.raises(RuntimeError, match=rf"is being written by egcbf reproduce \(pid {holder.pid}\)"),
        ):
            patch.setattr(rp.runner, "_stored", planned)
            rp.sweep(cfg, progress=False, log=lambda s: None)
    finally:
        holder.kill()
        holder.wait()
    rp.sweep(cfg, progress=False, log=lambda s: None)  # released when its process died


def test_sigterm_stops_a_sweep_like_ctrl_c():
    import os
    import signal
    import time

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt, match="signal"):
        with rp.runner._TermAsInterrupt():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # the handler interrupts this at once
    assert signal.getsignal(signal.SIGTERM) == before


def test_process_pool_yields_finished_cells_and_failures(first):
    """The process backend (spawned workers) returns each cell's outcome, a failing one as its traceback."""
    cfg, records = first
    cells = list(records)[:2]
    tasks = [rp.CellTask(cell=c, area=cfg.area_for(c), episodes=1, seed=3, max_steps=2, device="cpu") for c in cells]
    broken = dataclasses.replace(tasks[0], device="no-such-device")
    got = {t.cell: (res, err) for t, res, err in rp.workers.execute([broken, tasks[1]], "process", 2)}
    assert got[cells[0]][0] is None and "no-such-device" in got[cells[0]][1]
    assert got[cells[1]][1] is None and 0 <= got[cells[1]][0]["row"]["safe_rate"] <= 1


def test_process_pool_survives_a_dying_worker():
    """A worker killed mid-cell (kill -9, out of memory) fails that cell alone; every other cell, including the one
    that ran beside it, is still computed, and the sweep's iterator ends instead of waiting forever."""
    import pool_helpers

    cell = Cell("dcbf", 0, 2)
    seeds = [pool_helpers.DIE, 1, 2, 3, 4]
    tasks = [rp.CellTask(cell=cell, area=1.0, episodes=1, seed=s, max_steps=1, device="cpu") for s in seeds]
    got = {t.seed: (res, err) for t, res, err in rp.workers.run_processes(tasks, 2, pool_helpers.die_or_answer)}
    assert sorted(got) == sorted(seeds)
    assert got[pool_helpers.DIE][0] is None and "died" in got[pool_helpers.DIE][1]
    assert all(got[s] == ({"seed": s, "pid": got[s][0]["pid"]}, None) for s in seeds[1:])


def test_process_pool_ends_when_a_worker_dies_before_its_cell_starts():
    """A worker that dies before the cell it took starts (here: unpickling the task) still fails only that cell,
    and the iterator ends instead of building new pools forever."""
    import signal

    import pool_helpers

    cell = Cell("dcbf", 0, 2)
    tasks = [rp.CellTask(cell=cell, area=1.0, episodes=1, seed=s, max_steps=1, device="cpu") for s in (1, 2, 3)]
    tasks[1] = dataclasses.replace(tasks[1], device=pool_helpers.DiesWhenUnpickled())

    def hung(*_):
        raise TimeoutError("the pool kept rebuilding")

    old = signal.signal(signal.SIGALRM, hung)
    signal.alarm(240)
    try:
        got = {t.seed: (res, err) for t, res, err in rp.workers.run_processes(tasks, 2, pool_helpers.die_or_answer)}
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    assert sorted(got) == [1, 2, 3] and got[2][0] is None and "died" in got[2][1]
    assert got[1][1] is None and got[3][1] is None


def test_process_pool_closing_stops_its_workers_at_once():
    """Closing the iterator (an interruption) terminates the cells in progress instead of awaiting them."""
    import os
    import time

    import pool_helpers

    cell = Cell("dcbf", 0, 2)
    seeds = (1, pool_helpers.SLEEP, pool_helpers.SLEEP)
    tasks = [rp.CellTask(cell=cell, area=1.0, episodes=1, seed=s, max_steps=1, device="cpu") for s in seeds]
    outcomes = rp.workers.run_processes(tasks, 2, pool_helpers.die_or_answer)
    task, res, _ = next(outcomes)
    assert task.seed == 1
    t0 = time.perf_counter()
    outcomes.close()
    assert time.perf_counter() - t0 < 20
    for pid in {res["pid"]}:  # the worker that answered was stopped with the pool
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


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
    for extra in (" --max-steps 9", " --device=cuda", " --device cuda:0", " --robot unicycle", " --batch 2", " --x"):
        (base / "run.json").write_text(json.dumps(run | {"command": run["command"] + extra}))
        assert rp.import_baseline(cfg.baselines, cell, key) is None, extra
    for extra in (" --device cpu", " --dtype=float32", " --no-progress", " --out o --overwrite"):
        (base / "run.json").write_text(json.dumps(run | {"command": run["command"] + extra}))
        assert rp.import_baseline(cfg.baselines, cell, key) is not None, extra
    (base / "run.json").write_text(json.dumps(run | {"area": None}))
    assert rp.import_baseline(cfg.baselines, cell, key) is None


def test_report_sections_paper_numbers_and_figures(first, tmp_path, monkeypatch):
    cfg, records = first
    contour = pytest.importorskip("egcbf.viz.contour")
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
    for name in ("summary", "table", "scalability", "convergence", "contour", "provenance"):
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

    # a second report in the same folder draws its own figures and leaves the first report's alone
    before = {p.name: p.read_bytes() for p in (tmp_path / "docs" / "figures").iterdir()}
    other = tmp_path / "docs" / "other.md"
    rp.write_report(cfg, rp.load_cells(cfg), other)
    assert "figures/other_scalability.png" in other.read_text() and "figures/other_contour.png" in other.read_text()
    assert (tmp_path / "docs" / "figures" / "other_scalability.png").stat().st_size > 0
    assert all((tmp_path / "docs" / "figures" / n).read_bytes() == b for n, b in before.items())


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
    with pytest.raises(FileNotFoundError, match=r"egcbf train --algo gcbf\+ --seed 0 --out runs/gcbf\+-s0"):
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
    args += ["--train-seeds", "0", "--scale-sizes", "none"]
    res = CliRunner().invoke(app, args)  # every cell exists: nothing is recomputed
    assert res.exit_code == 0, res.output
    assert f"{len(records)} of {len(records)} cells" in res.output and "EGCBF+" in report.read_text()
    res = CliRunner().invoke(app, [*args, "--report-only"])
    assert res.exit_code == 0, res.output
    # the report of other settings than the stored cells' is refused, not written as all-pending
    other = [a if a != "2" else "9" for a in args]  # --episodes 9
    res = CliRunner().invoke(app, [*other, "--report-only"])
    assert res.exit_code == 2 and "were made with other settings" in res.output and "episodes 2 (stored)" in res.output
    res = CliRunner().invoke(app, other)  # and the sweep refuses to overwrite them
    assert res.exit_code == 2 and "--recompute" in res.output


def test_training_seeds_and_scalability_cells(checkpoints, tmp_path):
    cfg = _cfg(checkpoints, tmp_path / "out", methods=("egcbf+", "nominal"), obstacles=0, train_seeds=(0, 1))
    cfg = SweepConfig(**{**cfg.__dict__, "seed_methods": ("egcbf+",), "scale_sizes": (4,), "scale_reference": 2,
                         "scale_agent_episodes": 6, "long_steps": 7, "long_methods": ("egcbf+",)})  # fmt: skip
    l4 = cfg.scale_area(4)
    assert l4 == pytest.approx(1.5 * 2 ** (1 / 3), abs=1e-4)
    expected = {Cell("egcbf+", 0, n, s) for s in (0, 1) for n in (2, 3)} | {Cell("nominal", 0, n) for n in (2, 3)}
    expected |= {Cell("egcbf+", 0, 4, s, l4) for s in (0, 1)} | {Cell("nominal", 0, 4, None, l4)}
    long_ = {Cell("egcbf+", 0, 4, s, l4, "none", 7) for s in (0, 1)}  # the second horizon: its methods only
    assert set(cfg.cells()) == expected | long_ and set(cfg.long_cells()) == long_
    paths = {c.path(cfg.out).relative_to(cfg.out).as_posix() for c in cfg.cells()}
    assert {"egcbf+_obs0/N2.json", "egcbf+-s1_obs0/N2.json", "scale/egcbf+-s1_obs0/N4.json"} <= paths
    assert "scale-7-steps/egcbf+-s1_obs0/N4.json" in paths
    assert len(paths) == len(expected | long_)
    records = rp.sweep(cfg, progress=False, log=lambda s: None)
    assert set(records) == expected | long_
    long_rec = records[Cell("egcbf+", 0, 4, 1, l4, "none", 7)]
    assert long_rec["key"]["max_steps"] == 7 and long_rec["meta"]["max_steps"] == 7
    assert records[Cell("egcbf+", 0, 4, 1, l4)]["key"]["max_steps"] == 5  # the sweep's own horizon
    scale = records[Cell("egcbf+", 0, 4, 1, l4)]
    assert scale["key"]["episodes"] == 2 and scale["key"]["area"] == l4 and scale["meta"]["train_seed"] == 1
    assert scale["row"]["num_episodes"] == 2
    # a seed-1 cell is what `egcbf eval --checkpoint CHECKPOINTS/seeds/egcbf+-s1` computes
    ctrl, tcfg = load_controller(checkpoints / "seeds" / "egcbf+-s1")
    assert tcfg.seed == 1
    rows, _ = evaluate(lambda c: ctrl, [4], area_size=l4, episodes=2, seed=3, max_steps=5, show_progress=False,
                       env_overrides=dict(tcfg.env_overrides))  # fmt: skip
    assert _metrics(scale["row"]) == _metrics(rows[0])
    rows, _ = evaluate(lambda c: ctrl, [4], area_size=l4, episodes=2, seed=3, max_steps=7, show_progress=False,
                       env_overrides=dict(tcfg.env_overrides))  # fmt: skip
    assert _metrics(long_rec["row"]) == _metrics(rows[0])  # the long horizon's cell: the same episodes, 7 steps
    s0, s1 = (records[Cell("egcbf+", 0, 2, s)]["key"]["checkpoint_sha256"] for s in (0, 1))
    assert s0 != s1
    # the report: the mean over the seeds with its 95 % interval, the scalability rows, a summary from the cells
    report = tmp_path / "reproduction.md"
    rp.write_report(cfg, records, report)
    text = report.read_text()
    assert "EGCBF+ (2 seeds)" in text and "Scalability past Table I" in text and f"l = {l4:g}" in text
    horizon = text.split("<!-- horizon:begin -->")[1].split("<!-- horizon:end -->")[0]
    long_rows = [records[Cell("egcbf+", 0, 4, s, l4, "none", 7)]["row"] for s in (0, 1)]
    long_safe = Stat([r["safe_rate"] for r in long_rows], [0, 1], [r["per_episode"]["safe_rate"] for r in long_rows])
    assert "Safe % (7 steps)" in horizon and long_safe.text() in horizon and "| pending" not in horizon
    assert "nominal (no CBF)" not in horizon  # not among the long horizon's methods
    rows = [records[Cell("egcbf+", 0, 3, s)]["row"] for s in (0, 1)]
    cell = Stat([r["safe_rate"] for r in rows], [0, 1], [r["per_episode"]["safe_rate"] for r in rows])
    assert cell.interval is not None and cell.text() in text and " [" in cell.text()

    # the summary follows each method from N = scale_reference (Table I) to the largest fixed-density N
    def one(c):
        r = records[c]["row"]
        return Stat([r["safe_rate"]], None, [r["per_episode"]["safe_rate"]]).text()

    nominal_2, nominal_4 = one(Cell("nominal", 0, 2)), one(Cell("nominal", 0, 4, None, l4))
    assert f"nominal (no CBF) {nominal_2} % at N = 2 to {nominal_4} % at N = 4 (l = {l4:g} m)" in text


def test_stat_text():
    assert Stat([0.5]).text() == "50.0"
    assert Stat([0.9, 0.95, 1.0]).text() == "95.0 (90.0-100.0)"
    with pytest.raises(ValueError):
        Stat([])


def test_stat_text_with_per_episode_values_is_the_two_level_bootstrap_interval():
    """With every cell's per-episode values the text is the mean and its 95 % interval over training seeds and
    episodes (:func:`egcbf.evaluate.bootstrap.mean_ci`, deterministic); without them the min-max over seeds."""
    from egcbf.evaluate.bootstrap import mean_ci
    from egcbf.reproduce.stats import SeedRow, stat

    runs = [[1.0, 0.9, 0.8, 1.0], [0.7, 0.9, 1.0, 0.6], [1.0, 1.0, 0.95, 0.9]]
    values = [sum(r) / len(r) for r in runs]
    st = Stat(values, [0, 1, 2], runs)
    iv = mean_ci(runs)
    assert st.interval == iv and iv.low < st.mean < iv.high
    assert st.text() == f"{pct(st.mean)} [{pct(iv.low)}, {pct(iv.high)}]" == Stat(values, [0, 1, 2], runs).text()
    rows = [SeedRow(k, {"safe_rate": v, "per_episode": {"safe_rate": r}}, {}) for k, (v, r) in enumerate(zip(values,
            runs))]  # fmt: skip
    assert stat(rows, "safe_rate").text() == st.text()
    rows[1] = SeedRow(1, {"safe_rate": values[1]}, {})  # a cell computed before per-episode values were kept
    assert stat(rows, "safe_rate").interval is None and stat(rows, "safe_rate").text() == Stat(values).text()
    with pytest.raises(ValueError, match="runs"):
        Stat(values, None, runs[:2])


def test_rates_near_100_and_small_costs_keep_their_digits():
    """A rate below 1 never prints as 100.0 (dCBF-QP at N = 512: 0.999765625), one above 0 never as 0.0, and a
    cost above 0 never as 0.000."""
    assert pct(0.999765625) == "99.98" and pct(1.0) == "100.0" and pct(0.0) == "0.0"
    assert pct(0.99999) == "99.999" and pct(0.99949) == "99.9" and pct(1e-5) == "0.001"
    assert Stat([0.999765625]).text() == "99.98"
    assert Stat([0.9996, 1.0]).text() == "99.98 (99.96-100.0)"
    assert number(0.000234375) == "0.00023" and number(0.0) == "0.000" and number(0.0039, 2) == "0.0039"
    assert number(1.2014) == "1.201"


def test_checkpoint_of_the_wrong_seed_is_refused(checkpoints, tmp_path):
    root = tmp_path / "ck"
    shutil.copytree(checkpoints, root)
    shutil.copytree(root / "egcbf+", root / "seeds" / "egcbf+-s2")  # a seed-0 run filed as seed 2
    with pytest.raises(ValueError, match="trained with seed 0, expected seed 2"):
        rp.find_method_checkpoint(root, "egcbf+", 2)
    assert rp.find_method_checkpoint(root, "egcbf+", 1).train_seed == 1
    res = CliRunner().invoke(app, ["reproduce", "--methods", "egcbf+", "--train-seeds", "0,x"])
    assert res.exit_code == 2 and "--train-seeds" in res.output
    res = CliRunner().invoke(app, ["reproduce", "--methods", "egcbf+", "--seed-methods", "dcbf"])
    assert res.exit_code == 2 and "Error: --seed-methods must be among the learned" in res.output
    res = CliRunner().invoke(app, ["reproduce", "--methods", "egcbf+", "--area", "-1"])
    assert res.exit_code == 2 and "Error: --area must be > 0, got -1.0" in res.output
    res = CliRunner().invoke(app, ["reproduce", "--methods", "egcbf+", "--scale-agent-episodes", "0"])
    assert res.exit_code == 2 and "Error: --scale-agent-episodes must be >= 1" in res.output


def test_default_outputs_stay_out_of_the_users_docs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = ["reproduce", "--methods", "nominal", "--obstacle-methods", "nominal", "--num-agents", "2", "--area", "1.5"]
    args += ["--obstacles", "0", "--episodes", "1", "--max-steps", "2", "--train-seeds", "0", "--scale-sizes", "none"]
    res = CliRunner().invoke(app, [*args, "--no-progress"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "out" / "reproduction" / "reproduction.md").exists()
    assert (tmp_path / "out" / "reproduction" / "cells" / "nominal_obs0" / "N2.json").exists()
    assert not (tmp_path / "docs").exists()


def test_real_ray_backend_matches_the_process_backend(first):
    """The `ray` extra (installed with `dev`): a local Ray with two CPUs runs the cells as tasks (the checkpoint's
    bytes travel with each task) and gives the serial sweep's numbers."""
    ray = pytest.importorskip("ray")
    cfg, records = first
    sub = dict(methods=("egcbf+", "nominal"), obstacles=0, num_agents=(3,))
    serial = {c: _metrics(r["row"]) for c, r in records.items() if c.method == "egcbf+" and c in set(
        SweepConfig(**{**cfg.__dict__, **sub}).cells())}  # fmt: skip
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        ray_cfg = SweepConfig(**{**cfg.__dict__, **sub, "backend": "ray", "out": cfg.out.parent / "real-ray"})
        remote = rp.sweep(ray_cfg, progress=False, log=lambda s: None)
    finally:
        ray.shutdown()
    assert {c: _metrics(r["row"]) for c, r in remote.items() if c.method == "egcbf+"} == serial
    assert {c.method for c in remote} == {"egcbf+", "nominal"}
    log = json.loads((ray_cfg.out / "sweep.json").read_text())
    assert log[-1]["backend"] == "ray" and log[-1]["computed"] == len(remote)


# ------------------------------------------------------------------------------------------------ report, synthetic
def _row(n: int, safe: float, **kw) -> dict:
    row = dict(num_agents=n, safe_rate=safe, reach_rate=1.0, success_rate=safe, cost=1 - safe, cost_min=0.0)
    row.update(cost_max=2 * (1 - safe), reward=-1.0, collision_steps=3 * (1 - safe), step_ms_median=1.0)
    return row | kw


def _rec(cell: Cell, row: dict, **meta) -> dict:
    """A cell record as the sweep writes it (no files needed: the report reads only these)."""
    base = dict(train_seed=cell.train_seed, wall_s=10.0, finished="2026-01-01T00:10:00+00:00", device="cpu")
    base["machine"] = {"cpu": "Test CPU", "cores": 4, "threads": 1}
    key = {"method": cell.method, "num_agents": cell.num_agents, "checkpoint_sha256": meta.pop("sha", None)}
    return {"key": key, "row": row, "meta": base | meta}


def _synthetic_cfg(tmp_path, **kw) -> SweepConfig:
    base = dict(methods=("egcbf+",), num_agents=(8,), obstacles=0, train_seeds=(2, 0, 1), seed_methods=("egcbf+",))
    base.update(scale_sizes=(), checkpoints=tmp_path / "no-checkpoints", out=tmp_path / "cells", baselines=None)
    return SweepConfig(**(base | kw))


def test_seed_labels_follow_their_own_seeds(tmp_path):
    """Seeds 0 and 2 done, seed 1 pending, train_seeds unsorted: each value keeps its own seed's label, and rows
    made of some of the seeds say so."""
    cfg = _synthetic_cfg(tmp_path)
    records = {Cell("egcbf+", 0, 8, s): _rec(Cell("egcbf+", 0, 8, s), _row(8, v)) for s, v in ((0, 0.9), (2, 0.8))}
    summary = rp.summary_markdown(cfg, records)
    assert "seed 0 90.0 %, seed 2 80.0 % (spread 10.0 points) (2 of 3 seeds of EGCBF+ so far)" in summary
    assert "seed 1" not in summary
    rows = rp.stats.seed_rows(records, "egcbf+", 0, 8, False)
    assert [r.train_seed for r in rows] == [0, 2] and [r.row["safe_rate"] for r in rows] == [0.9, 0.8]
    table = rp.table_markdown(cfg, records)
    assert "| EGCBF+ (2 of 3 seeds) | 85.0 (80.0-90.0) |" in table  # the per-N table's row label
    assert "85.0 (80.0-90.0) [2 of 3 seeds]" in table  # the glance tables' value


def test_summary_wording_qps_differences_and_partial_scale_rows(tmp_path):
    """The QP bullet covers Table I only ("100 % safe at every N" when it is); the E-method difference is
    "EGCBF+ minus GCBF+", says which side has one training seed, and gives fixed-density N their l; the scalability
    table marks partial seed averages and shows the QP slack / failed counts and collision steps."""
    cfg = _synthetic_cfg(
        tmp_path,
        methods=("gcbf+", "dcbf", "ccbf", "egcbf+"),
        num_agents=(8, 512),
        train_seeds=(0, 1),
        seed_methods=("gcbf+",),
        scale_sizes=(1024,),
    )
    l1024 = cfg.scale_area(1024)
    records = {}
    for n, area in ((8, None), (512, None), (1024, l1024)):
        for m, safe in (("dcbf", 0.999765625 if n == 1024 else 1.0), ("ccbf", 1.0)):
            qp = {"qp_slack_steps": 7, "qp_failed": 1} if m == "dcbf" else {"qp_slack_steps": 0, "qp_failed": 0}
            cell = Cell(m, 0, n, None, area)
            records[cell] = _rec(cell, _row(n, safe, **qp))
        for s, safe in ((0, 0.8), (1, 0.9)):
            cell = Cell("gcbf+", 0, n, s, area)
            if not (n == 1024 and s == 1):  # GCBF+ seed 1 pending at N = 1024
                records[cell] = _rec(cell, _row(n, safe))
        cell = Cell("egcbf+", 0, n, 0, area)
        records[cell] = _rec(cell, _row(n, 0.95))
    summary = rp.summary_markdown(cfg, records)
    assert "dCBF-QP over Table I's N = 8 to 512: 100 % safe at every N, 100 % successful at every N" in summary
    assert "cCBF-QP over Table I's N = 8 to 512: 100 % safe at every N" in summary
    assert "99.98 % at N = 1024 (l = " in summary  # the fixed-density cell has its own bullet
    assert "What equivariance buys" not in summary
    line = next(x for x in summary.splitlines() if "**EGCBF+ minus GCBF+**" in x)
    assert "N = 512: +10.0 (EGCBF+: one training seed, outside GCBF+'s seed range 80.0-90.0)" in line
    assert f"N = 1024 (l = {l1024:g} m): +15.0" in line and "(1 of 2 seeds of GCBF+ so far)" in line
    table = rp.table_markdown(cfg, records)
    scale = table.split("### Scalability past Table I")[1]
    assert f"| 1024 (l = {l1024:g} m) | GCBF+ (1 of 2 seeds) | 80.0 |" in scale
    assert "| QP slack / failed |" in scale and "| 7 / 1 |" in scale and "| 0 / 0 |" in scale
    assert "coll. steps" in scale
    assert "| 99.98 |" in scale and "0.00023 (" in scale  # never 100.0 nor 0.000 for what is not
    n512 = table.split("**N = 512**")[1].split("**N =")[0]
    assert "| GCBF+ (2 seeds) | 85.0 (80.0-90.0) |" in n512 and "| 7 / 1 |" in n512


def test_table_intro_timings_come_from_the_cells_and_invocations(tmp_path):
    """The step-ms note is built from the cells' machines and the recorded invocations; imported cells' timings
    are marked with a dagger; nothing about the machine is typed in."""
    cfg = _synthetic_cfg(tmp_path, methods=("egcbf+", "nominal"), num_agents=(8, 16), train_seeds=(0,))
    cfg.out.mkdir(parents=True)
    invocation = {"command": "egcbf reproduce --workers 3", "started": "2026-01-01T00:00:00+00:00", "wall_s": 900.0,
                  "status": "finished", "backend": "process", "workers": 3, "threads_per_cell": 1}  # fmt: skip
    (cfg.out / "sweep.json").write_text(json.dumps([invocation]))
    records = {}
    for n in (8, 16):
        cell = Cell("egcbf+", 0, n, 0)
        late = {"finished": "2026-01-02T00:00:00+00:00"} if n == 16 else {}  # no recorded invocation spans it
        records[cell] = _rec(cell, _row(n, 0.9), sha="a" * 64, checkpoint="ck/egcbf+", checkpoint_step=5, **late)
        cell = Cell("nominal", 0, n)
        machine = {"cpu": "Other CPU", "threads": 1}
        records[cell] = _rec(cell, _row(n, 0.5), imported_from="baselines/nominal", wall_s=None, machine=machine)
    table = rp.table_markdown(cfg, records)
    assert "two cells at once" not in table and "2-core" not in table
    assert "1 on Test CPU (4 cores), 1 torch thread per cell, up to 3 cells at a time" in table
    assert "1 on Test CPU (4 cores), 1 torch thread per cell, cells at a time not recorded" in table
    assert "† imported cells" in table and "2 on Other CPU, 1 torch thread" in table
    assert "| 1.00† |" in table and "| 1.00 |" in table
    prov = rp.provenance_markdown(cfg, records)
    assert "`egcbf reproduce --workers 3`" in prov and "up to 3 cells at a time" in prov
    assert "1 in invocations not in `sweep.json`" in prov
    assert "No readable checkpoint under" in prov and "aaaaaaaaaaaa (2)" in prov  # report-only without checkpoints


def test_empty_settings_are_worded_not_printed_empty(tmp_path):
    """No obstacle method, no scale sizes and no obstacles: no empty obstacle table, no empty size list, no
    "with 0 obstacles"."""
    cfg = _synthetic_cfg(tmp_path, methods=("dcbf",), num_agents=(8,), obstacles=8, obstacle_methods=("egcbf+",))
    records = {Cell("dcbf", 0, 8): _rec(Cell("dcbf", 0, 8), _row(8, 1.0))}
    table = rp.table_markdown(cfg, records)
    assert "obstacles (not in Table I)" not in table
    assert "Scalability past Table I: not run" in table and "()" not in table
    assert "obstacle setting: none" in rp.provenance_markdown(SweepConfig(**{**cfg.__dict__, "obstacles": 0}), {})
    text = rp.figures.scalability_section(SweepConfig(**{**cfg.__dict__, "obstacles": 0}), records,
                                          tmp_path / "r.md", tmp_path / "fig")  # fmt: skip
    assert "obstacles" not in text and "fixed density" not in text


def test_report_intro_gives_the_command_for_this_report(tmp_path, monkeypatch):
    """The intro names --out, --report and the non-default flags (a block of its own, placed below the title of
    a report written before it existed), and the file is written once, atomically."""
    cfg = _synthetic_cfg(tmp_path, methods=("dcbf",), num_agents=(8, 16), train_seeds=(0,), episodes=20)
    assert rp.regenerate_command(cfg, "docs/r e.md") == (
        f"egcbf reproduce --out {cfg.out} --report 'docs/r e.md' --methods dcbf --num-agents 8,16 --obstacles 0 "
        f"--episodes 20 --train-seeds 0 --seed-methods egcbf+ --scale-sizes none --checkpoints {cfg.checkpoints} "
        "--report-only"
    )
    report = tmp_path / "docs" / "r.md"
    report.parent.mkdir()
    report.write_text("# Reproducing Table I and the scalability study\n\nan old intro\n")
    writes = []
    real = rp.report.write_text_atomic
    monkeypatch.setattr(rp.report, "write_text_atomic", lambda p, t: writes.append(p) or real(p, t))
    monkeypatch.setattr(rp.report, "contour_section", lambda *a: "no contour")
    monkeypatch.setattr(rp.report, "convergence_section", lambda *a: "no curves")
    records = {Cell("dcbf", 0, 8): _rec(Cell("dcbf", 0, 8), _row(8, 1.0))}
    rp.write_report(cfg, records, report)
    rp.write_report(cfg, records, report)
    text = report.read_text()
    assert writes == [report, report]
    assert text.startswith("# Reproducing Table I and the scalability study\n\n<!-- intro:begin -->")
    assert text.count("<!-- intro:begin -->") == 1 and "an old intro" in text
    assert f"    {rp.regenerate_command(cfg, report)}\n" in text
    rp.write_report(cfg, records, report, regenerate_command="make reproduce-report")
    assert "    make reproduce-report\n" in report.read_text()


def test_provenance_flags_cells_of_another_checkpoint(first):
    """Cells whose checkpoint sha256 differs from the checkpoint now in CHECKPOINTS are counted and flagged."""
    cfg, records = first
    changed = dict(records)
    cell = next(c for c in records if c.method == "egcbf+")
    changed[cell] = {**records[cell], "key": {**records[cell]["key"], "checkpoint_sha256": "f" * 64}}
    prov = rp.provenance_markdown(cfg, changed)
    assert "ffffffffffff (1) **not the current checkpoint**" in prov
    assert "**1 cell(s) were computed with a checkpoint other than the one now in" in prov
    assert "not the current checkpoint" not in rp.provenance_markdown(cfg, records)


# ------------------------------------------------------------------------------------------------ run-time filters
@pytest.fixture(scope="module")
def filtered(checkpoints, tmp_path_factory):
    """A finished sweep of EGCBF+ behind the dCBF filter (with and without obstacles) and of the nominal controller
    behind it: its config and records."""
    cfg = _cfg(checkpoints, tmp_path_factory.mktemp("filtered"), methods=("egcbf+:dcbf", "nominal:dcbf"),
               num_agents=(3,), obstacle_methods=("egcbf+:dcbf",), episodes=1)  # fmt: skip
    return cfg, rp.sweep(cfg, command="egcbf reproduce (filtered)", progress=False, log=lambda s: None)


def test_filtered_cells_equal_egcbf_eval_with_the_filter(filtered, tmp_path):
    """A METHOD:FILTER cell is what `egcbf eval --checkpoint ... --filter FILTER` computes (`--controller nominal` for
    the nominal one), in a folder of its own, and records the filter as eval's run.json does."""
    cfg, records = filtered
    assert set(records) == {Cell("egcbf+:dcbf", 0, 3, 0), Cell("egcbf+:dcbf", 1, 3, 0), Cell("nominal:dcbf", 0, 3)}
    paths = {c.path(cfg.out).relative_to(cfg.out).as_posix() for c in records}
    assert paths == {"egcbf+_dcbf_obs0/N3.json", "egcbf+_dcbf_obs1/N3.json", "nominal_dcbf_obs0/N3.json"}
    common = ["--num-agents", "3", "--area", "1.5", "--episodes", "1", "--seed", "3", "--max-steps", "5"]
    for cell, source in ((Cell("egcbf+:dcbf", 1, 3, 0), ["--checkpoint", str(cfg.checkpoints / "egcbf+")]),
                         (Cell("nominal:dcbf", 0, 3), ["--controller", "nominal"])):  # fmt: skip
        out = tmp_path / cell.method.replace(":", "_")
        args = ["eval", *source, "--filter", "dcbf", "--obstacles", str(cell.obstacles), *common, "--out", str(out)]
        res = CliRunner().invoke(app, [*args, "--no-progress"])
        assert res.exit_code == 0, res.output
        run, row = json.loads((out / "run.json").read_text()), json.loads((out / "metrics.json").read_text())[0]
        stored = json.loads(cell.path(cfg.out).read_text())
        assert run["controller"] == cell.method and _metrics(stored["row"]) == _metrics(row)
        for part in ("key", "meta"):
            assert stored[part]["filter"] == run["filter"] == "dcbf"
            assert stored[part]["filter_config"] == run["filter_config"]
        assert "filter_active" in stored["row"] and "qp_slack_steps" in stored["row"]
    learned, nominal = records[Cell("egcbf+:dcbf", 0, 3, 0)], records[Cell("nominal:dcbf", 0, 3)]
    assert learned["key"]["checkpoint_sha256"] == rp.find_method_checkpoint(cfg.checkpoints, "egcbf+").sha256
    assert learned["meta"]["checkpoint"] == str(cfg.checkpoints / "egcbf+") and learned["meta"]["train_seed"] == 0
    assert nominal["key"]["checkpoint_sha256"] is None and nominal["meta"]["train_seed"] is None


def test_filtered_cells_resume_without_recomputing(filtered, monkeypatch):
    cfg, records = filtered

    def boom(task):
        raise AssertionError(f"recomputed {task.cell}")

    monkeypatch.setattr(rp.workers, "run_cell", boom)
    assert rp.sweep(cfg, progress=False, log=lambda s: None) == records
    assert json.loads((cfg.out / "sweep.json").read_text())[-1]["reused"] == len(records)
    assert rp.load_cells(cfg) == records


def test_filtered_rows_in_the_tables_summary_and_figure(filtered, tmp_path):
    cfg, records = filtered
    table = rp.table_markdown(cfg, records)
    n3 = table.split("**N = 3**")[1].split("###")[0]
    assert "| EGCBF+ + dCBF filter |" in n3 and "| nominal + dCBF filter |" in n3 and "% changed)" in n3
    assert "| QP slack / failed |" in n3 and n3.count("| - | - | - | - | - |") == 2  # not in the paper
    obstacles = table.split("### With 1 obstacles")[1]
    assert "| 3 | EGCBF+ + dCBF filter |" in obstacles and "nominal + dCBF filter" not in obstacles
    assert "Run-time safety filters (not in the paper" in table
    assert "**Behind run-time filters**" in rp.summary_markdown(cfg, records)
    assert "Run-time filter `dcbf` of 3 cell(s): barrier wang" in rp.provenance_markdown(cfg, records)
    assert rp.scalability_figure(cfg, records, tmp_path / "f.png").stat().st_size > 0
    # a filtered method with no cell yet shows as pending, like any other
    wide = dataclasses.replace(cfg, methods=(*cfg.methods, "egcbf+:prior"))
    assert "| EGCBF+ + prior-CBF filter | pending |" in rp.table_markdown(wide, records)


def test_filtered_methods_follow_their_base_methods_seeds_and_checkpoints(checkpoints, tmp_path, monkeypatch):
    cfg = _cfg(checkpoints, tmp_path / "out", methods=("egcbf+", "egcbf+:dcbf", "egcbf+:cbf", "nominal:dcbf"),
               obstacles=0, train_seeds=(0, 1), seed_methods=("egcbf+",), num_agents=(2,))  # fmt: skip
    assert cfg.seeds_for("egcbf+:dcbf") == cfg.seeds_for("egcbf+") == (0, 1) and cfg.seeds_for("nominal:dcbf") == (
        None,
    )
    assert cfg.checkpoint_runs() == [("egcbf+", 0), ("egcbf+", 1)]
    paths = {c.path(cfg.out).relative_to(cfg.out).as_posix() for c in cfg.cells()}
    assert {"egcbf+-s1_obs0/N2.json", "egcbf+_dcbf-s1_obs0/N2.json", "egcbf+_cbf_obs0/N2.json"} <= paths
    assert "nominal_dcbf_obs0/N2.json" in paths and len(paths) == len(cfg.cells()) == 7
    ckpts = rp.validate(cfg)
    keys = {c: rp.store.wanted_key(cfg, c, ckpts) for c in cfg.cells()}
    assert keys[Cell("egcbf+:dcbf", 0, 2, 1)]["checkpoint_sha256"] == ckpts["egcbf+", 1].sha256
    # an unfiltered cell's key is the one of the sweep before the filtered methods: its stored cells are found
    assert list(keys[Cell("egcbf+", 0, 2, 1)]) == [
        "method", "obstacles", "num_agents", "area", "episodes", "seed", "max_steps", "checkpoint_sha256"
    ]  # fmt: skip
    assert keys[Cell("egcbf+:cbf", 0, 2, 0)]["filter_config"] == {
        "alpha": 1.0,
        "margin": 0.0,
        "qp_solver": "active_set",
    }
    # the learned-CBF filter needs the soft-min CBF head: refused before any cell runs
    plain = types.SimpleNamespace(model=types.SimpleNamespace(interface="accel", cbf_head="mlp", cbf_z_symmetric=False))
    import egcbf.train.checkpoint

    monkeypatch.setattr(egcbf.train.checkpoint, "read_config", lambda path: plain)
    with pytest.raises(ValueError, match=r"egcbf\+:cbf cannot use the checkpoint .*soft-min CBF head"):
        rp.runner._check_filters(cfg, ckpts)
    rp.runner._check_filters(dataclasses.replace(cfg, methods=("egcbf+:dcbf",)), ckpts)  # dcbf reads no CBF


def test_committed_results_are_found_with_the_filtered_methods_in_the_default_set():
    """The default sweep holds the filtered methods; every committed cell of docs/results/reproduction keeps its
    file and its key (nothing stored is recomputed or reported as made with other settings). Cells of the shipped
    EGCBF+ and GCBF+ checkpoints may still be pending (they were swapped for the per-edge fine-tuned policies and are
    recomputed across sessions), as may the MARL baselines' (added later); every other learned and hand-crafted cell
    of the sweep before the filtered methods is stored."""
    out = Path(__file__).resolve().parents[2] / "docs" / "results" / "reproduction"
    stored = sorted(out.rglob("N*.json"))
    if not stored:
        pytest.skip("no committed reproduction cells")
    cfg = SweepConfig(out=out)
    assert set(rp.FILTERED) <= set(cfg.methods) & set(cfg.obstacle_methods) & set(cfg.scale_methods)
    unswapped = tuple(m for m in cfg.methods if m not in (*rp.FILTERED, *rp.MARL) and m not in cfg.seed_methods)
    before = dataclasses.replace(
        cfg,
        methods=unswapped,
        obstacle_methods=tuple(m for m in cfg.obstacle_methods if m in unswapped),
        scale_methods=tuple(m for m in cfg.scale_methods if m in unswapped),
        long_steps=None,  # (the second horizon came later)
    )
    found = rp.load_cells(cfg)
    assert set(before.cells()) <= set(found) <= set(cfg.cells())
    assert len(found) == len(stored) and not rp.mismatched_cells(cfg)
    for cell, rec in found.items():
        assert rec["key"] == rp.cell_key(cfg, cell, rec["key"]["checkpoint_sha256"])
    assert all(c.path(out).exists() for c in before.cells())
    _assert_cells_of_their_checkpoints(found, out.parents[2] / "checkpoints")


def _assert_cells_of_their_checkpoints(found: dict, checkpoints: Path) -> None:
    """Every learned cell was computed with the checkpoint that ``checkpoints`` holds now (none is stale)."""
    shas = {}
    for cell, rec in found.items():
        if cell.train_seed is None:
            continue
        run = (cell.base, cell.train_seed)
        if run not in shas:
            shas[run] = rp.find_method_checkpoint(checkpoints, *run).sha256
        assert rec["key"]["checkpoint_sha256"] == shas[run], (cell, rec["meta"].get("checkpoint"))


def test_the_paper_target_archive_is_complete_and_found():
    """docs/results/paper-target holds every cell of EGCBF+ and GCBF+ (three training seeds, Table I with and without
    obstacles, the scalability study) for the policies trained with the paper's QP target, which
    checkpoints/paper-target keeps: each is found under its key (docs/paper_target.md is generated from them)."""
    root = Path(__file__).resolve().parents[2]
    out = root / "docs" / "results" / "paper-target"
    if not (root / "checkpoints" / "paper-target").exists():
        pytest.skip("no paper-target checkpoints")
    cfg = SweepConfig(
        methods=("gcbf+", "egcbf+"),
        obstacle_methods=("gcbf+", "egcbf+"),
        scale_methods=("gcbf+", "egcbf+"),
        checkpoints=root / "checkpoints" / "paper-target",
        out=out,
        long_steps=None,
    )
    found = rp.load_cells(cfg)
    assert set(found) == set(cfg.cells()) and len(cfg.cells()) == 90
    assert not rp.mismatched_cells(cfg)
    _assert_cells_of_their_checkpoints(found, cfg.checkpoints)


def test_the_fine_tuned_archive_cells_are_of_their_checkpoints():
    """docs/results/fine-tuned holds the cells computed for the per-edge fine-tuned policies while they shipped
    (checkpoints/fine-tuned; the shipped policies are their weight averages with checkpoints/paper-target): each is
    found under its key and was computed with the checkpoint that directory holds (docs/fine_tuned.md)."""
    root = Path(__file__).resolve().parents[2]
    if not (root / "checkpoints" / "fine-tuned").exists():
        pytest.skip("no fine-tuned checkpoints")
    methods = ("egcbf+", "gcbf+", "egcbf+:dcbf")
    cfg = SweepConfig(
        methods=methods,
        obstacle_methods=methods,
        scale_methods=methods,
        checkpoints=root / "checkpoints" / "fine-tuned",
        out=root / "docs" / "results" / "fine-tuned",
        long_steps=None,
    )
    found = rp.load_cells(cfg)
    stored = sorted(cfg.out.glob("**/N*.json"))
    assert len(found) == len(stored) == 79 and not rp.mismatched_cells(cfg)
    _assert_cells_of_their_checkpoints(found, cfg.checkpoints)


def test_reproduce_command_takes_the_filtered_names(filtered, tmp_path):
    from egcbf.cli.reproduce import _LONG_METHODS, _REPRO_METHODS, _REPRO_OBSTACLE_METHODS

    assert tuple(_REPRO_METHODS.split(",")) == SweepConfig().methods == SweepConfig().scale_methods == rp.METHODS
    assert tuple(_REPRO_OBSTACLE_METHODS.split(",")) == SweepConfig().obstacle_methods
    assert tuple(_LONG_METHODS.split(",")) == SweepConfig().long_methods
    res = CliRunner().invoke(app, ["reproduce", "--methods", "egcbf+:bogus,egcbf+:dcbf"])
    assert res.exit_code == 2 and "unknown method(s) ['egcbf+:bogus']" in res.output
    assert "egcbf+:dcbf, gcbf+:dcbf, egcbf+:cbf, egcbf+:prior, nominal:dcbf" in res.output
    cfg, records = filtered
    report = tmp_path / "r.md"
    args = ["reproduce", "--methods", "egcbf+:dcbf,nominal:dcbf", "--obstacle-methods", "egcbf+:dcbf"]
    args += ["--num-agents", "3", "--area", "1.5", "--obstacles", "1", "--episodes", "1", "--seed", "3"]
    args += ["--max-steps", "5", "--train-seeds", "0", "--scale-sizes", "none", "--checkpoints", str(cfg.checkpoints)]
    args += ["--out", str(cfg.out), "--report", str(report), "--no-progress"]
    res = CliRunner().invoke(app, args)  # every cell exists: nothing is recomputed
    assert res.exit_code == 0, res.output
    assert f"{len(records)} of {len(records)} cells" in res.output and "EGCBF+ + dCBF filter" in report.read_text()


def test_method_lists_naming_methods_not_run_are_refused(first, tmp_path):
    cfg, _ = first
    base = ["reproduce", "--methods", "egcbf+,dcbf", "--num-agents", "2", "--area", "1.5", "--episodes", "2",
            "--checkpoints", str(cfg.checkpoints), "--out", str(tmp_path / "o"), "--report", str(tmp_path / "r.md"),
            "--scale-sizes", "none", "--no-progress", "--report-only"]  # fmt: skip
    for flag, value in (("--obstacle-methods", "egcbf+,gcbf+"), ("--seed-methods", "gcbf+"),
                        ("--scale-methods", "dcbf,ccbf")):  # fmt: skip
        res = CliRunner().invoke(app, [*base, flag, value])
        assert res.exit_code == 2, res.output
        assert f"{flag} names" in res.output and "which --methods does not run" in res.output, res.output
    # a filtered method runs its base method's training seeds: naming the base in --seed-methods is right
    ok = [a if a != "egcbf+,dcbf" else "egcbf+:dcbf,dcbf" for a in base]
    res = CliRunner().invoke(app, [*ok, "--seed-methods", "egcbf+"])
    assert "--seed-methods names" not in res.output, res.output


def test_report_only_names_a_truncated_cell_file(first, tmp_path):
    import shutil

    cfg, records = first
    out = tmp_path / "cells"
    shutil.copytree(cfg.out, out)
    victim = next(iter(records)).path(out)
    victim.write_text(victim.read_text()[:40])  # truncated
    args = ["reproduce", "--methods", "egcbf+,dcbf", "--num-agents", "2,3", "--area", "1.5", "--obstacles", "1"]
    args += ["--obstacle-methods", "egcbf+", "--episodes", "2", "--seed", "3", "--max-steps", "5", "--no-progress"]
    args += ["--checkpoints", str(cfg.checkpoints), "--out", str(out), "--report", str(tmp_path / "r.md")]
    args += ["--train-seeds", "0", "--scale-sizes", "none", "--report-only"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "1 cell file(s) cannot be read" in res.output and str(victim) in res.output, res.output


def test_convergence_draws_the_run_a_fine_tuned_checkpoint_started_from(checkpoints, tmp_path, monkeypatch):
    """A checkpoint whose config names ``init_from`` (fine-tuned) is drawn with the curve of the run it started
    from (its whole training), and the caption says so; without ``init_from`` its own metrics.csv is drawn."""
    from egcbf.reproduce.figures import convergence_section
    from egcbf.viz import curves

    ckpts = tmp_path / "checkpoints"
    shutil.copytree(checkpoints, ckpts)
    start = tmp_path / "start"
    shutil.copytree(checkpoints / "egcbf+", start)
    cfg_file = ckpts / "egcbf+" / "config.json"
    cfg_file.write_text(json.dumps({**json.loads(cfg_file.read_text()), "init_from": str(start)}))
    drawn = []
    monkeypatch.setattr(curves, "training_curves", lambda runs, png: drawn.append(runs) or png)
    cfg = _cfg(ckpts, tmp_path / "out")
    text = convergence_section(cfg, tmp_path / "r.md", tmp_path / "figures")
    assert drawn[-1]["EGCBF+"][0] == start
    assert "EGCBF+: the runs the shipped policies were fine-tuned from" in text
    cfg_file.write_text(json.dumps({k: v for k, v in json.loads(cfg_file.read_text()).items() if k != "init_from"}))
    text = convergence_section(cfg, tmp_path / "r.md", tmp_path / "figures")
    assert drawn[-1]["EGCBF+"][0] == ckpts / "egcbf+" and "fine-tuned from" not in text


def test_several_sweeps_run_as_one_queue_and_each_is_recorded(first, tmp_path, monkeypatch):
    """sweep_many: two sweeps into one directory through one pool give each sweep's records as sweep() would, the
    cell they share is computed once, each sweep has its own finished entry in sweep.json; sweeps that do not share
    a directory and backend are refused."""
    cfg, records = first
    out = tmp_path / "many"
    a = SweepConfig(**{**cfg.__dict__, "methods": ("dcbf",), "obstacles": 0, "out": out, "workers": 2})
    b = SweepConfig(**{**cfg.__dict__, "methods": ("dcbf", "egcbf+"), "obstacles": 0, "num_agents": (3,),
                       "out": out, "workers": 2})  # fmt: skip
    messages = []
    ra, rb = rp.sweep_many([a, b], commands=["first", "second"], progress=False, log=messages.append)
    serial = {c: _metrics(r["row"]) for c, r in records.items() if c.obstacles == 0}
    assert {c: _metrics(r["row"]) for c, r in ra.items()} == {c: serial[c] for c in a.cells()}
    assert {c: _metrics(r["row"]) for c, r in rb.items()} == {c: serial[c] for c in b.cells()}
    assert len([m for m in messages if "safe" in m]) == len(set(a.cells()) | set(b.cells()))  # the shared one once
    runs = json.loads((out / "sweep.json").read_text())
    assert [(r["command"], r["status"], r["computed"]) for r in runs] == [
        ("first", "finished", 2),
        ("second", "finished", 2),
    ]
    with pytest.raises(ValueError, match="differ in out"):
        rp.sweep_many([a, SweepConfig(**{**b.__dict__, "out": tmp_path / "elsewhere"})])
    assert rp.sweep_many([]) == []
    monkeypatch.setitem(sys.modules, "ray", _fake_ray())  # the same queue on Ray
    remote = [SweepConfig(**{**c.__dict__, "backend": "ray", "out": tmp_path / "ray"}) for c in (a, b)]
    ra2, rb2 = rp.sweep_many(remote, progress=False, log=lambda s: None)
    assert {c: _metrics(r["row"]) for c, r in {**ra2, **rb2}.items()} == {c: serial[c] for c in {**ra, **rb}}


def test_an_unreadable_sweep_history_is_moved_aside_not_overwritten(tmp_path):
    from egcbf.reproduce.store import read_invocations, record_invocation

    (tmp_path / "sweep.json").write_text('[{"command": "egcbf reproduce", "status": "fini')  # cut by a full disk
    with pytest.warns(UserWarning, match="moved aside"):
        assert record_invocation(tmp_path, {"command": "new", "status": "running"}, 3) == 0
    aside = list(tmp_path.glob("sweep.json.unreadable-*"))
    assert len(aside) == 1 and aside[0].read_text().startswith('[{"command": "egcbf reproduce"')
    assert read_invocations(tmp_path) == [{"command": "new", "status": "running"}]


def test_pending_seeds_of_two_methods_are_one_note():
    """A difference of two methods, each with pending training seeds, says so once, naming both."""
    from egcbf.reproduce.plan import SweepConfig
    from egcbf.reproduce.stats import Stat, so_far

    cfg = SweepConfig(train_seeds=(0, 1, 2))
    one, three = Stat([0.9], [0]), Stat([0.9, 0.8, 0.7], [0, 1, 2])
    assert so_far(one, cfg, "egcbf+", (one, "gcbf+")) == " (1 of 3 seeds of EGCBF+, 1 of 3 of GCBF+ so far)"
    assert so_far(three, cfg, "egcbf+", (one, "gcbf+")) == " (1 of 3 seeds of GCBF+ so far)"
    assert so_far(three, cfg, "egcbf+", (three, "gcbf+")) == ""


def test_a_quoted_block_is_rewritten_only_where_the_page_has_its_markers(tmp_path):
    """`quote_section` rewrites the block between a page's markers, leaves a page without them (or no page) alone;
    `relative_link` is the path from the page's folder."""
    from egcbf.io.report import quote_section, relative_link

    page, bare = tmp_path / "README.md", tmp_path / "plain.md"
    page.write_text("intro\n<!-- x:begin -->\nold\n<!-- x:end -->\ntail\n")
    bare.write_text("no markers\n")
    assert quote_section(page, "x", "new")
    assert page.read_text() == "intro\n<!-- x:begin -->\nnew\n<!-- x:end -->\ntail\n"
    assert not quote_section(bare, "x", "new") and bare.read_text() == "no markers\n"
    assert not quote_section(tmp_path / "absent.md", "x", "new") and not (tmp_path / "absent.md").exists()
    assert relative_link(tmp_path / "docs" / "r.md", page) == "docs/r.md"
    assert relative_link(tmp_path / "docs" / "fig.png", tmp_path / "docs" / "r.md") == "fig.png"


def test_the_long_horizon_flags(tmp_path):
    """``--long-steps`` takes a number of steps or ``none`` (then the sweep has no second horizon), refuses anything
    else, and the report-only regeneration command names it where it differs from the default."""
    base = ["reproduce", "--methods", "nominal", "--num-agents", "2", "--scale-sizes", "4", "--out",
            str(tmp_path / "cells"), "--report", str(tmp_path / "r.md"), "--report-only", "--no-progress"]  # fmt: skip
    res = CliRunner().invoke(app, [*base, "--long-steps", "soon"])
    assert res.exit_code == 2 and "--long-steps must be a number of steps or 'none'" in res.output
    res = CliRunner().invoke(app, [*base, "--long-methods", "egcbf+"])  # not among --methods
    assert res.exit_code == 2 and "--long-methods names egcbf+" in res.output
    cfg = SweepConfig(methods=("nominal",), long_steps=None, out=tmp_path / "cells")
    assert cfg.long_cells() == [] and "--long-steps none" in rp.provenance.regenerate_command(cfg, "r.md")
    cfg = SweepConfig(methods=("nominal",), out=tmp_path / "cells")
    assert {c.steps for c in cfg.long_cells()} == {384} and "--long-steps" not in rp.provenance.regenerate_command(
        cfg, "r.md"
    )
    with pytest.raises(ValueError, match="long_steps must be >= 1"):
        SweepConfig(long_steps=0)


def test_the_contour_gap_prints_round_off_as_its_bound():
    """An equivariance gap at float64 round-off prints the same on every CPU; a real one keeps its digits."""
    from egcbf.reproduce.figures import _gap

    assert _gap(1.33e-15) == _gap(6.4e-16) == "< 1e-12 (round-off)" and _gap(4.38e-2) == "4.38e-02"
