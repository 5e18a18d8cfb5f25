"""egcbf robustness: fault levels as egcbf reproduce sweeps (cells, keys, paths), the plan's controller groups, the
report from computed cells, and the command end to end."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch
from typer.testing import CliRunner

from egcbf.cli import app
from egcbf.faults import DEFAULT_FIELD, parse_faults
from egcbf.faults.spec import HANDLING_FIELDS
from egcbf.io.report import machine_info
from egcbf.reproduce import SweepConfig
from egcbf.reproduce.plan import cell_key
from egcbf.reproduce.provenance import machine_text
from egcbf.robustness import AXES, RobustnessConfig, axis, reads_sensing, state_level


def test_a_sweep_under_faults_keeps_its_cells_apart_and_the_perfect_world_unchanged(tmp_path):
    common = dict(methods=("nominal",), num_agents=(8,), obstacles=0, out=tmp_path, baselines=None, scale_sizes=())
    plain, faulty = SweepConfig(**common), SweepConfig(**common, faults="vel=0.02,pos=0.01")
    assert faulty.faults == "pos_noise=0.01,vel_noise=0.02"  # canonical: one spelling, one cell
    (c0,), (c1,) = plain.cells(), faulty.cells()
    assert c0.faults == "none" and c1.faults == faulty.faults
    assert c0.path(tmp_path) == tmp_path / "nominal_obs0" / "N8.json"
    assert c1.path(tmp_path) == tmp_path / "faults" / "pos_noise_0.01_vel_noise_0.02" / "nominal_obs0" / "N8.json"
    assert "faults" not in cell_key(plain, c0, None) and cell_key(faulty, c1, None)["faults"] == faulty.faults
    with pytest.raises(ValueError, match="unknown"):
        SweepConfig(faults="posx=1")


def test_the_plan_runs_the_perfect_world_first_and_message_faults_only_where_they_are_read():
    assert axis("field").specs() == ["none", DEFAULT_FIELD.spec()]
    assert all(a.levels[0] == 0 and a.specs()[0] == "none" for a in AXES)
    assert all(len(a.levels) >= 5 for a in AXES if not a.name.startswith("field"))
    assert reads_sensing("egcbf+") and not reads_sensing("ccbf") and not reads_sensing("nominal")
    assert state_level("default") == "pos_noise=0.01,vel_noise=0.02,thrust_gain=0.1,noncoop=0.05"
    cfg = RobustnessConfig(axes=("field", "loss"))
    sweeps = cfg.sweeps()
    assert sweeps[0][1] == "none" and set(sweeps[0][2].methods) == set(cfg.controllers)
    for _, spec, sw in sweeps[1:]:
        if "msg_loss" in spec:
            assert "ccbf" not in sw.methods and "nominal" not in sw.methods
    assert any(spec == state_level("default") and "ccbf" in sw.methods for _, spec, sw in sweeps)
    assert cfg.cell_spec("ccbf", "msg_loss=0.3") is None and cfg.cell_spec("egcbf+", "msg_loss=0.3") == "msg_loss=0.3"
    ray = RobustnessConfig(axes=("field",), backend="ray", workers=3, device="cuda")
    assert {(s.backend, s.workers, s.device, s.episodes) for _, _, s in ray.sweeps()} == {("ray", 3, "cuda", 20)}
    # per channel: the dCBF-QP reads messages but not the LiDAR (its obstacle rows come from the map), and so does
    # its filter of the nominal command; a policy behind the filter reads the LiDAR through its graph
    lidar = axis("lidar").specs()[2]
    assert cfg.cell_spec("dcbf", lidar) is None and cfg.cell_spec("egcbf+", lidar) == lidar
    assert cfg.cell_spec("egcbf+:dcbf", lidar) == lidar and cfg.cell_spec("nominal:dcbf", lidar) is None
    assert reads_sensing("egcbf+:dcbf") is True and reads_sensing("nominal:dcbf") == {"messages"}
    for m in ("dcbf", "nominal:dcbf"):
        assert cfg.cell_spec(m, DEFAULT_FIELD.spec()) == DEFAULT_FIELD.spec()
        assert cfg.cell_spec(m, "msg_loss=0.1,lidar_noise=0.1") == "msg_loss=0.1"
    both = parse_faults("msg_loss=0.1,lidar_noise=0.1").spec()
    assert cfg.cell_spec("egcbf+:dcbf", both) == both
    # the receivers' axes: the message handling goes with the messages (a controller without them runs the
    # state-level part, the very cell of the plain axis)
    held = axis("field_receivers").specs()[1]
    assert "msg_hold=5" in held and "msg_predict=1" in held and cfg.cell_spec("egcbf+", held) == held
    assert cfg.cell_spec("ccbf", held) == state_level("default")
    assert axis("loss_receivers").specs()[2] == "msg_loss=0.3,msg_hold=5,msg_predict=1"
    # the actuation fix acts on the agents' own estimates: every controller runs it, and its level 0 is the perfect
    # world
    ahead = axis("act_delay_predict")
    assert ahead.specs()[0] == "none" and ahead.specs()[2] == "act_delay=2,act_predict=1"
    assert all(cfg.cell_spec(m, ahead.specs()[2]) == ahead.specs()[2] for m in cfg.controllers)
    # every fix's axis is its fault axis again with the agents' handling added, level by level
    for fix in (a for a in AXES if a.fixes is not None):
        plain, handling = axis(fix.fixes), parse_faults(fix.handling())
        added = {k: v for k, v in handling.active().items()}
        assert fix.levels == plain.levels and fix.specs()[0] == "none" and added, fix.name
        assert all(parse_faults(o) == dataclasses.replace(parse_faults(p), **added)
                   for p, o in zip(plain.specs()[1:], fix.specs()[1:])), fix.name  # fmt: skip
        assert set(added) <= set(HANDLING_FIELDS)  # a fix adds handling, never a fault
    observed = axis("wind_observer")
    assert observed.handling() == "dist_obs=1" and observed.compared() == (axis("wind").specs()[2], observed.specs()[2])
    assert all(cfg.cell_spec(m, observed.specs()[2]) == observed.specs()[2] for m in cfg.controllers)


def test_robustness_command_computes_cells_and_writes_its_report(tmp_path):
    out, report = tmp_path / "cells", tmp_path / "robustness.md"
    args = ["robustness", "--axes", "field,thrust", "--controllers", "nominal", "--num-agents", "4",
            "--obstacles", "1", "--episodes", "2", "--max-steps", "4", "--out", str(out),
            "--report", str(report), "--figures", str(tmp_path / "fig"),
            "--workers", "1", "--no-progress"]  # fmt: skip
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    text = report.read_text()
    assert "## Default field conditions" in text and "| nominal (no CBF) | 4 | 0 |" in text
    assert "(all 12 cells computed)" in text
    where = text.split("## Where the cells were computed")[1]  # each stored cell counted once, with its machine
    assert f"| 12 | {machine_text(machine_info())}, torch {torch.__version__}, device cpu |" in where
    assert "| not `msg_loss`, `msg_delay` (" in text  # the nominal controller reads no messages
    choices = text.split("Under one fault")[1].split("## Where")[0]
    assert "- thrust gain error" in choices and "nominal (no CBF)" in choices  # every level of the axis computed
    cells = sorted(p.relative_to(out).as_posix() for p in out.rglob("N4.json"))
    assert "nominal_obs0/N4.json" in cells and any("thrust_gain_0.3" in c for c in cells)
    rec = json.loads((out / "nominal_obs1" / "N4.json").read_text())
    assert rec["row"]["num_episodes"] == 2
    # the receivers' fix: its own section, the message-reading controllers only, pending cells shown as such
    r = CliRunner().invoke(app, [*args, "--axes", "field,field_receivers", "--controllers", "nominal,dcbf",
                                 "--report-only"])  # fmt: skip
    assert r.exit_code == 0, r.output
    fixes = report.read_text().split("## Fixes")[1].split("## What to choose")[0]
    assert "| dCBF-QP | 4 | 0 | - | - | - |" in fixes and "nominal" not in fixes
    assert "rerun `egcbf robustness` to compute the rest" in report.read_text()  # a partial sweep says so
    assert (tmp_path / "fig" / "robustness_thrust.png").exists() and "(fig/robustness_thrust.png)" in text
    # the actuation fix: every controller, the two-step level without and with the prediction
    r = CliRunner().invoke(app, [*args, "--axes", "act_delay,act_delay_predict", "--controllers", "nominal"])
    assert r.exit_code == 0, r.output
    fixes = report.read_text().split("## Fixes: commanding")[1].split("## What to choose")[0]
    row = next(line for line in fixes.splitlines() if line.startswith("| nominal (no CBF) | 4 | 0 |"))
    assert "| - |" not in row  # both cells computed, so the paired change is there
    # the disturbance observer's fix: +-30 % thrust without and with it
    r = CliRunner().invoke(app, [*args, "--axes", "field,thrust,thrust_observer", "--controllers", "nominal"])
    assert r.exit_code == 0, r.output
    fixes = report.read_text().split("## Fixes: cancelling")[1].split("## What to choose")[0]
    assert "`thrust_gain=0.3`" in fixes
    advice = report.read_text().split("## What to choose")[1].split("## Where")[0]
    line = next(x for x in advice.splitlines() if x.startswith("- thrust gain error, agents observing"))
    assert "`dist_obs=1`" in line and "for nominal (no CBF)" in line and "measured at N = 4: 0 obstacles: " in line
    row = next(line for line in fixes.splitlines() if line.startswith("| nominal (no CBF) | 4 | 1 |"))
    assert "| - |" not in row
    before = (out / "nominal_obs1" / "N4.json").read_text()
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 0 and (out / "nominal_obs1" / "N4.json").read_text() == before  # reused, not rerun
    # the README beside the report's folder quotes the pick at the default field conditions, between its markers
    readme, moved = tmp_path / "README.md", tmp_path / "docs" / "robustness.md"
    readme.write_text("intro\n<!-- robustness-headline:begin -->\nold\n<!-- robustness-headline:end -->\ntail\n")
    r = CliRunner().invoke(app, [*args, "--report", str(moved), "--report-only"])
    assert r.exit_code == 0, r.output
    quoted = readme.read_text()
    assert quoted.startswith("intro\n") and quoted.endswith("tail\n") and "old" not in quoted
    assert "([docs/robustness.md](docs/robustness.md)" in quoted and "0 obstacles: **nominal (no CBF)**" in quoted
    assert "points against the fault-free run" in quoted and "N = 4, l = 4" in quoted
    bad = CliRunner().invoke(app, ["robustness", "--axes", "nope", "--plan"])
    assert bad.exit_code == 2 and "unknown" in bad.output


def test_failed_cells_do_not_stop_the_others_and_are_named(tmp_path, monkeypatch):
    """Every level's cells go to one queue (one sweep_many call, a command per level); the cells that raise are
    named at the end, after the report is written from the others."""
    import egcbf.reproduce as reproduce
    from egcbf.reproduce.runner import CellsFailed

    seen = []

    def fake_sweep_many(cfgs, commands=None, **kw):
        seen.append(([c.faults for c in cfgs], list(commands)))
        raise CellsFailed({c.cells()[0]: "Traceback\nImportError: no solver" for c in cfgs if c.faults != "none"})

    monkeypatch.setattr(reproduce, "sweep_many", fake_sweep_many)
    args = ["robustness", "--axes", "thrust", "--controllers", "nominal", "--num-agents", "4", "--out",
            str(tmp_path / "c"), "--report", str(tmp_path / "r.md"), "--figures", str(tmp_path / "f")]  # fmt: skip
    r = CliRunner().invoke(app, args)
    assert len(seen) == 1 and len(seen[0][0]) == 5 and seen[0][1] == ["egcbf robustness --axes thrust"] * 5
    assert r.exit_code == 1 and "4 cell(s) failed" in r.output and "faults thrust_gain=0.3" in r.output
    assert (tmp_path / "r.md").exists()


def test_the_committed_report_is_generated_from_the_committed_cells(tmp_path, monkeypatch):
    """docs/robustness.md is what `egcbf robustness --report-only` writes from the cells in docs/results/robustness
    (regenerate it whenever cells are committed), and the README quotes its current pick."""
    from pathlib import Path

    from egcbf.robustness import write_report

    root = Path(__file__).resolve().parents[2]
    monkeypatch.chdir(root)
    readme = tmp_path / "README.md"
    readme.write_text((root / "README.md").read_text())
    path = write_report(RobustnessConfig(), tmp_path / "docs" / "robustness.md", tmp_path / "docs" / "figures")
    assert path.read_text() == (root / "docs" / "robustness.md").read_text()
    assert readme.read_text() == (root / "README.md").read_text()


def _with_episodes(safe: list[float], success: list[float]) -> dict:
    """A cell's row with its per-episode safe and success rates (what the paired intervals read)."""
    return {"safe_rate": sum(safe) / len(safe), "success_rate": sum(success) / len(success),
            "per_episode": {"safe_rate": safe, "success_rate": success}}  # fmt: skip


def _rows(safe: float, success: float | None = None) -> dict:
    return {"safe_rate": safe, "success_rate": safe if success is None else success}


def test_the_advice_holds_a_level_only_with_every_milder_one():
    """A controller that drops below 99 % safe at a mild level and recovers at a harsher one does not hold the
    harsher one; the advice picks the controller that held every level up to it."""
    from egcbf.robustness.advice import advice

    cfg = RobustnessConfig(axes=("thrust",), controllers=("nominal", "ccbf"), num_agents=(4,), obstacles=1)
    safe = {"nominal": (1.0, 0.98, 0.995, 0.995, 0.995), "ccbf": (1.0, 0.995, 0.995, 0.98, 0.97)}
    cells = {(m, spec, 4, k): _rows(safe[m][i]) for m in safe for i, spec in enumerate(axis("thrust").specs())
             for k in (0, 1)}  # fmt: skip
    line = next(x for x in advice(cfg, cells) if x.startswith("- thrust gain error"))
    assert "up to 0.1 (" in line and "**cCBF-QP**" in line and "none stays 99 % safe up to 0.2" in line, line


def test_a_fix_the_recommended_controller_does_not_perceive_is_said_so_and_n_a_wins_over_0():
    from egcbf.robustness.advice import advice
    from egcbf.robustness.report import _breaking_levels

    cfg = RobustnessConfig(axes=("field", "field_receivers", "loss"), controllers=("nominal", "ccbf"),
                           num_agents=(4,), obstacles=1)  # fmt: skip
    cells = {(m, spec, 4, k): _rows(0.995 if m == "ccbf" else 0.5) for m in cfg.controllers
             for spec in axis("field").specs() for k in (0, 1)}  # fmt: skip
    lines = advice(cfg, cells)
    assert any("**cCBF-QP**" in x for x in lines)
    fix = next(x for x in lines if x.startswith("- default field conditions, receivers"))
    assert "does not change cCBF-QP" in fix and "pending" not in fix
    table = _breaking_levels(cfg, {(m, "none", 4, 0): _rows(0.5) for m in cfg.controllers}, 4, 0)
    row = next(x for x in table if x.startswith("| message loss"))
    assert row.endswith("| n/a | n/a |"), row  # nominal is below 99 % without faults, but reads no messages


def test_a_break_within_its_episode_band_of_the_threshold_is_marked_borderline():
    """'*' marks the first level below a threshold only when that level's 95 % band over episodes still reaches it:
    one agent-episode short of 99 % is borderline, a collapse is not."""
    from egcbf.robustness.report import _breaking_levels

    cfg = RobustnessConfig(axes=("thrust",), controllers=("nominal", "ccbf"), num_agents=(4,), obstacles=1)
    specs = axis("thrust").specs()
    clean = _with_episodes([1.0] * 20, [1.0] * 20)
    short = _with_episodes([1.0] * 19 + [0.8], [1.0] * 20)  # 99.0 % -> just below with one bad episode
    short = {**short, "safe_rate": 0.9899}
    collapse = _with_episodes([0.5] * 20, [0.5] * 20)
    cells = {("nominal", specs[0], 4, 0): clean, ("nominal", specs[1], 4, 0): short,
             ("ccbf", specs[0], 4, 0): clean, ("ccbf", specs[1], 4, 0): collapse}  # fmt: skip
    for m in ("nominal", "ccbf"):
        for spec in specs[2:]:
            cells[m, spec, 4, 0] = collapse
    row = next(x for x in _breaking_levels(cfg, cells, 4, 0) if x.startswith("| thrust gain error"))
    level = f"{axis('thrust').levels[1]:g}"
    assert row.endswith(f"| {level}* / {axis('thrust').levels[2]:g} | {level} / {level} |"), row


def test_bad_inputs_and_a_partial_plan_into_the_committed_report_are_refused_before_anything_runs(tmp_path):
    base = ["robustness", "--axes", "thrust", "--controllers", "nominal", "--num-agents", "4", "--out",
            str(tmp_path / "c"), "--report", str(tmp_path / "r.md"), "--figures", str(tmp_path / "f")]  # fmt: skip
    for flag, value, says in (("--area", "-1", "--area"), ("--max-steps", "0", "--max-steps"),
                              ("--checkpoints", str(tmp_path / "none"), "none")):  # fmt: skip
        r = CliRunner().invoke(app, [*base, "--controllers", "nominal,egcbf+", flag, value])
        assert r.exit_code == 2 and "Error:" in r.output and says in r.output, r.output
        assert not (tmp_path / "c").exists() and not (tmp_path / "r.md").exists()
    narrowed = ["robustness", "--axes", "thrust", "--out", str(tmp_path / "c"), "--report-only"]
    for own in ([], ["--report", str(tmp_path / "r.md")], ["--figures", str(tmp_path / "f")]):
        r = CliRunner().invoke(app, [*narrowed, *own])  # its figures would replace the whole plan's too
        assert r.exit_code == 2 and "is the whole plan's report" in " ".join(r.output.split()), r.output
        assert not (tmp_path / "r.md").exists() and not (tmp_path / "f").exists()


def test_the_report_reads_only_cells_made_with_its_settings(tmp_path):
    """A stored cell counts only for the settings it was made with (episodes, seed, area, episode length)."""
    from egcbf.reproduce.plan import cell_key
    from egcbf.reproduce.store import write_json
    from egcbf.robustness.cells import _cell, load_records

    cfg = RobustnessConfig(axes=("thrust",), controllers=("nominal",), num_agents=(4,), episodes=2, out=tmp_path)
    spec = axis("thrust").specs()[1]
    cell = _cell("nominal", spec, 4, 0)
    key = cell_key(cfg.sweep(spec, ("nominal",)), cell, None)
    write_json(cell.path(tmp_path), {"key": key, "row": {"safe_rate": 1.0, "success_rate": 1.0}, "meta": {}})
    assert ("nominal", spec, 4, 0) in load_records(cfg)
    for other in (dataclasses.replace(cfg, episodes=3), dataclasses.replace(cfg, seed=1),
                  dataclasses.replace(cfg, max_steps=100)):  # fmt: skip
        assert ("nominal", spec, 4, 0) not in load_records(other)


def test_the_fix_advice_follows_the_paired_intervals():
    """A fix is advised on only when the paired intervals show it helps and does not cost safety; one that costs
    safety is advised off, and one whose intervals all include 0 is said to change nothing measurable."""
    from egcbf.robustness.advice import advice

    cfg = RobustnessConfig(axes=("field", "thrust", "thrust_observer"), controllers=("nominal",), num_agents=(4,),
                           obstacles=1)  # fmt: skip
    after = axis("thrust_observer").compared()[1]

    safe, success = [0.99, 1.0, 1.0, 0.995, 1.0, 0.99, 1.0, 1.0], [0.8, 0.9, 0.85, 0.8, 0.9, 0.85, 0.8, 0.9]
    cases = {
        "turn on `dist_obs=1` for nominal (no CBF)": _with_episodes(safe, [x + 0.05 for x in success]),  # as safe
        "leave `dist_obs=1` off for nominal (no CBF): it costs safety": _with_episodes(
            [x - 0.1 for x in safe], [1.0] * 8
        ),
        "`dist_obs=1`: no change measurable within these episodes for nominal (no CBF)": _with_episodes(safe, success),
        "`dist_obs=1` for nominal (no CBF): not judged": {"safe_rate": 0.5, "success_rate": 1.0},  # no episodes
    }
    for says, fixed in cases.items():
        cells = {("nominal", spec, 4, k): _with_episodes(safe, success) for a in ("field", "thrust")
                 for spec in axis(a).specs() for k in (0, 1)}  # fmt: skip
        cells |= {("nominal", after, 4, k): fixed for k in (0, 1)}
        line = next(x for x in advice(cfg, cells) if x.startswith("- thrust gain error, agents observing"))
        assert says in line and "measured at N = 4: 0 obstacles: " in line, line
        hint = next(x for x in advice(cfg, cells) if x.startswith("- thrust gain error, up to"))
        assert f"The agents' fix, at 0.3 (+- fraction), the last level: {says}" in hint, hint


def test_an_axis_fix_is_measured_where_the_pick_breaks_and_a_pending_larger_n_is_said():
    """The per-axis hint measures the agents' fix at the level where the chosen controller first drops below 99 %
    safe (there the fix matters; at a level it holds there is little to gain) and names that level; a pick read at
    a smaller N because the larger one is incomplete says so."""
    from egcbf.robustness.advice import advice

    cfg = RobustnessConfig(axes=("thrust", "thrust_observer"), controllers=("nominal", "ccbf"), num_agents=(4, 8),
                           obstacles=1)  # fmt: skip
    specs, fixed = axis("thrust").specs(), axis("thrust_observer").specs()
    holds, breaks = [1.0] * 8, [1.0] * 4 + [0.9] * 4
    cells = {}
    for k in (0, 1):
        for i, spec in enumerate(specs):
            cells["nominal", spec, 4, k] = _with_episodes(breaks, breaks)
            cells["ccbf", spec, 4, k] = _with_episodes(breaks if i >= 3 else holds, holds)
            cells["nominal", fixed[i], 4, k] = _with_episodes(breaks, breaks)
            cells["ccbf", fixed[i], 4, k] = _with_episodes(holds, holds)
    cells["ccbf", specs[0], 8, 0] = _with_episodes(holds, holds)  # N = 8 begun, not complete
    hint = next(x for x in advice(cfg, cells) if x.startswith("- thrust gain error, up to"))
    assert "up to 0.1 (+- fraction): **cCBF-QP**" in hint and "N = 4 (N = 8 pending)" in hint, hint
    assert "The agents' fix, at 0.2 (+- fraction), where it first drops below 99 % safe: turn on" in hint, hint
    assert "95.00 -> 100.00 % safe" in hint, hint  # the mean of breaks, not of a level cCBF-QP holds


def test_the_correlated_field_has_its_own_pick_and_says_what_it_costs_the_plain_pick():
    """``field_correlated`` (the default field conditions with correlated errors and bursty losses) gets its own
    pick, and the line says how much safety the plain conditions' pick loses there (paired)."""
    from egcbf.robustness.advice import advice

    cfg = RobustnessConfig(axes=("field", "field_correlated"), controllers=("nominal", "ccbf"), num_agents=(4,),
                           obstacles=1)  # fmt: skip
    plain, shaped = axis("field").specs()[1], axis("field_correlated").specs()[1]
    assert "noise_tau=0.5" in shaped and "msg_burst=5" in shaped
    good, worse = [1.0] * 8, [1.0] * 4 + [0.96] * 4
    cells = {}
    for k in (0, 1):
        for m in cfg.controllers:
            cells[m, "none", 4, k] = _with_episodes(good, good)
        cells["nominal", plain, 4, k] = _with_episodes([0.9] * 8, [0.9] * 8)
        cells["ccbf", plain, 4, k] = _with_episodes(good, good)
        cells["nominal", shaped, 4, k] = _with_episodes(good, [0.5] * 8)
        cells["ccbf", shaped, 4, k] = _with_episodes(worse, worse)
    line = next(x for x in advice(cfg, cells) if x.startswith("- default field conditions, errors correlated"))
    assert "N = 4, 0 obstacles: **nominal (no CBF)**" in line, line  # the only one >= 99 % safe there
    assert "The plain conditions' pick, cCBF-QP: 100.00 -> 98.00 % safe (-2.00 [" in line, line


def test_a_filtered_pick_says_which_faults_reach_only_its_policy():
    """The dCBF filter's obstacle rows come from the map: a LiDAR fault reaches the filtered controller's policy
    only, which the advice says where it picks it; message faults reach the filter too, so nothing is said."""
    from egcbf.robustness.advice import _filter_spared

    lidar = axis("lidar").specs()[2]
    assert "does not read `lidar_noise`, `lidar_drop`: those faults reach only its policy" in _filter_spared(
        "egcbf+:dcbf", lidar
    )
    assert _filter_spared("egcbf+:dcbf", axis("loss").specs()[2]) == ""
    assert _filter_spared("egcbf+", lidar) == ""


def test_the_default_field_pick_is_compared_with_its_runner_up_and_safety_without_arrival_is_said():
    """The recommendation states the pick minus the runner-up (paired intervals; a tie when both include 0), and an
    axis pick that is safe because its agents do not arrive says so."""
    from egcbf.robustness.advice import advice

    cfg = RobustnessConfig(axes=("field", "thrust"), controllers=("nominal", "ccbf"), num_agents=(4,), obstacles=1)

    safe = [0.99, 1.0, 1.0, 0.995, 1.0, 0.99, 1.0, 1.0]
    few = [0.3, 0.4, 0.35, 0.3, 0.4, 0.35, 0.3, 0.4]
    arrive = {"nominal": few, "ccbf": [0.31, *few[1:]]}  # cCBF-QP: 0.01 more in one episode
    cells = {(m, spec, 4, k): _with_episodes(safe, arrive[m]) for m in cfg.controllers for a in ("field", "thrust")
             for spec in axis(a).specs() for k in (0, 1)}  # fmt: skip
    lines = advice(cfg, cells)
    pick = next(x for x in lines if x.startswith("- default field conditions, N = 4, 0 obstacles"))
    spared = "ran without `msg_loss`, `msg_delay`, which it does not perceive: not like for like"
    assert "**cCBF-QP**" in pick and f"safe; {spared})." in pick, pick
    assert f"Minus the runner-up, nominal (no CBF) ({spared}): safe +0.00 [+0.00, +0.00]" in pick, pick
    assert "not distinguishable within these episodes" in pick, pick
    thrust = next(x for x in lines if x.startswith("- thrust gain error, up to"))
    assert "Fewer than half of its agents reach their goals there." in thrust, thrust
