"""The certificate (egcbf.certify): the exact binomial bounds, every count on hand-made trajectories, the barriers'
values and their SE2xR invariance (hypothesis, float64 within 1e-9; the learned barrier in float32 within 1e-5),
rollouts that match the evaluation's, the resumable sweep, the report and the CLI."""

import dataclasses
import functools
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from dyn_helpers import moving_scene
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from egcbf.algo.config import TrainConfig
from egcbf.certify import (
    BrakingBarrier,
    CertifyConfig,
    LearnedBarrier,
    Trajectory,
    clopper_pearson,
    count_rates,
    load_cells,
    pending,
    pool_counts,
    rate,
    roll_out,
    sweep,
    verdict,
    write_report,
)
from egcbf.cli import app
from egcbf.control.controllers import make_controller
from egcbf.control.filters import DCBF_FILTER_BARRIER, FilterConfig, FilteredController
from egcbf.env import EnvConfig, SwarmState
from egcbf.env.graph import GROUP
from egcbf.env.obstacles import Obstacles
from egcbf.evaluate.episodes import run_episodes
from egcbf.nn import CBFNet
from groupcanon.testing import strategies as gst

ROOT = Path(__file__).resolve().parents[2]
F64 = torch.float64


# ---------------------------------------------------------------------------------------------------- bounds
@pytest.mark.parametrize("n", [1, 10, 1000, 100_000])
def test_zero_failures_bound_is_the_closed_form(n):
    assert clopper_pearson(0, n)[1] == pytest.approx(1 - 0.05 ** (1 / n), rel=1e-9)


def test_bounds_known_values_and_shape():
    lo, hi = clopper_pearson(100, 100_000)
    assert lo == 0 and hi == pytest.approx(1.18e-3, rel=0.01)  # the reference's "about 1.2e-3"
    lo2, hi2 = clopper_pearson(5, 10, two_sided=True)
    assert lo2 == pytest.approx(1 - hi2, rel=1e-9) and 0.18 < lo2 < 0.19  # symmetric; textbook [0.187, 0.813]
    assert clopper_pearson(0, 0) == (0.0, 1.0) and clopper_pearson(3, 3)[1] == 1.0
    with pytest.raises(ValueError):
        clopper_pearson(4, 3)


@given(k=st.integers(0, 50), extra=st.integers(0, 500))
@settings(max_examples=30, deadline=None)
def test_the_interval_holds_the_rate_and_shrinks_with_n(k, extra):
    n = k + extra + 1
    lo, hi = clopper_pearson(k, n, two_sided=True)
    assert lo <= k / n <= hi
    assert clopper_pearson(k, n)[1] <= hi  # the one-sided 95 % bound is inside the two-sided 95 % interval
    assert clopper_pearson(2 * k, 2 * n)[1] <= hi + 1e-12


# ---------------------------------------------------------------------------------------------------- counts
def _traj(h, coll, bad=None, dt=0.1):
    h = torch.tensor(h, dtype=F64).T[:, None, :]  # given (N, T + 1) -> (T + 1, 1, N)
    coll = torch.tensor(coll, dtype=torch.bool).T[:, None, :]
    bad = None if bad is None else torch.tensor(bad, dtype=torch.bool).T[:, None, :]
    return Trajectory({"h": h}, coll, bad, dt)


def test_counts_on_a_hand_made_trajectory():
    """Two agents, T = 6 steps, W = 2: agent 0 claims safety until it collides at t = 3 (two misses: t = 1, 2);
    agent 1 is warned (h < 0) at t = 2 and stays safe (conservative), and its h falls too fast at t = 0, 1."""
    h = [[0.5, 0.5, 0.4, 0.3, -0.1, -0.1, -0.1],
         [1.0, 0.5, -0.2, -0.2, 0.3, 0.3, 0.3]]  # fmt: skip
    coll = [[0, 0, 0, 1, 1, 0, 0],
            [0, 0, 0, 0, 0, 0, 0]]  # fmt: skip
    c = count_rates(_traj(h, coll), "h", lambda x: 1.0 * x, window=2, stride=1)
    assert c["states"] == 12  # t = 0 .. 5, two agents
    assert (c["unsafe"], c["unsafe_claimed"]) == (2, 1)  # agent 0 at t = 3 (h 0.3) and t = 4 (h -0.1)
    assert (c["preceding"], c["missed"], c["missed_agents"]) == (2, 2, 1)  # agent 0 at t = 1, 2
    # claims: agent 0 at t = 0 .. 3, agent 1 at t = 0, 1, 4, 5; condition h' - h >= -0.1 h: agent 0 fails at
    # t = 1, 2, 3 (drops of 0.1, 0.1, 0.4), agent 1 at t = 0, 1 (drops of 0.5, 0.7), not at 4, 5 (constant)
    assert (c["claims"], c["violated"], c["violated_agents"]) == (8, 5, 2)
    # known claims: t + 2 <= 6, i.e. t <= 4, or a collision within 2; false-safe: in collision or preceding
    assert c["false_safe"] == 3 and c["claims_known"] == 7
    # negatives with t <= 4: agent 0 at t = 4 (in collision: not cautious), agent 1 at t = 2, 3 (safe: cautious)
    assert (c["negatives_known"], c["cautious"]) == (3, 2)
    assert (c["starts"], c["breaches"], c["breaches_collided"]) == (2, 2, 1)  # agent 0 left at 4, collided at 4
    assert c["filter_states"] == 0 and c["violated_or_bad"] == c["violated"]
    assert sum(c["histogram"].values()) == c["claims_known"] + c["negatives_known"] + 0  # every known state
    r = rate(c, "miss")
    assert r["k"] == 2 and r["n"] == 2 and r["rate"] == 1.0 and r["upper"] == 1.0


def test_filter_status_and_stride_and_pooling():
    h = [[0.5] * 9, [0.5] * 9]
    coll = [[0] * 9, [0] * 9]
    bad = [[1, 0, 0, 0, 1, 0, 0, 0], [0] * 8]
    c = count_rates(_traj(h, coll, bad), "h", lambda x: x, window=2, stride=4)
    assert c["states"] == 4 and c["filter_states"] == 4 and c["filter_bad"] == 2 and c["violated_or_bad"] == 2
    assert c["violated"] == 0  # a constant h never violates a decrease condition
    p = pool_counts([c, c])
    assert p["filter_bad"] == 4 and p["states"] == 8
    assert p["histogram"] == {k: 2 * v for k, v in c["histogram"].items()}
    assert verdict(p).startswith("not valid")  # 4 of 8 QPs failed; and no collision: the miss bound is 1


def test_an_infinite_barrier_never_violates():
    inf = math.inf
    c = count_rates(_traj([[inf, inf, 0.2, inf], [0.3, 0.3, 0.3, 0.3]], [[0] * 4, [0] * 4]), "h", lambda x: x,
                    window=1, stride=1)  # fmt: skip
    assert c["violated"] == 0 and c["claims"] == 6


# ---------------------------------------------------------------------------------------------------- barriers
def _pair_state(d, closing, obstacles=None):
    """Two agents on the x axis ``d`` apart, approaching each other at ``closing`` m/s (float64)."""
    cfg = EnvConfig(num_agents=2, num_envs=1, area_size=4.0, num_obstacles=0)
    x = torch.zeros(1, 2, 18, dtype=F64)
    x[..., 3:12] = torch.eye(3, dtype=F64).reshape(9)
    x[0, 0, 0], x[0, 1, 0] = 1.0, 1.0 + d
    x[0, 0, 12], x[0, 1, 12] = closing / 2, -closing / 2
    x[..., 2] = 1.0
    obs = obstacles or Obstacles(torch.zeros(1, 0, 3, dtype=F64), torch.zeros(1, 0, dtype=F64))
    return SwarmState(x, x[..., :3].clone(), obs), cfg


def test_braking_barrier_values():
    b = BrakingBarrier(DCBF_FILTER_BARRIER)
    D, A = DCBF_FILTER_BARRIER.safe_distance, DCBF_FILTER_BARRIER.brake_accel
    state, cfg = _pair_state(0.3, 1.0)
    h = b.values(state, cfg)
    assert torch.allclose(h, torch.full((1, 2), math.sqrt(2 * 2 * A * (0.3 - D)) - 1.0, dtype=F64), atol=1e-12)
    h_in = b.values(*_pair_state(0.11, -1.0))  # inside D (moving apart): d - D < 0 whatever the velocity
    assert torch.allclose(h_in, torch.full((1, 2), 0.11 - D, dtype=F64), atol=1e-12)
    far = b.values(*_pair_state(cfg.comm_radius + 0.1, 5.0))
    assert torch.isinf(far).all() and (far > 0).all()
    ball = Obstacles(torch.tensor([[[1.0, -0.3, 1.0]]], dtype=F64), torch.tensor([[0.1]], dtype=F64))
    h_obs = b.values(*_pair_state(2.0, 0.0, ball))
    gap = 0.3 - 0.1 - DCBF_FILTER_BARRIER.agent_radius - DCBF_FILTER_BARRIER.margin
    assert h_obs[0, 0] == pytest.approx(math.sqrt(2 * A * gap), abs=1e-12) and torch.isinf(h_obs[0, 1])


def _scene(seed, obstacles=2):
    cfg = EnvConfig(num_agents=6, num_envs=2, area_size=1.2, num_obstacles=obstacles, n_rays=8, lidar_max_hits=4)
    return moving_scene(cfg, seed), cfg


@given(g=gst.elements(GROUP, batch=(2,)), seed=st.integers(0, 2**20))
@settings(max_examples=10, deadline=None)
def test_braking_barrier_is_invariant(g, seed):
    state, cfg = _scene(seed)
    a, b = (BrakingBarrier(DCBF_FILTER_BARRIER).values(s, cfg) for s in (state, state.transform(g)))
    fin = torch.isfinite(a)
    assert torch.equal(fin, torch.isfinite(b)) and fin.any()
    assert (a[fin] - b[fin]).abs().max() <= 1e-9


@functools.cache
def _cbf(dtype=F64):
    torch.manual_seed(0)
    cfg = dataclasses.replace(TrainConfig.preset("egcbf+", "cpu").model, hidden=16, head_hidden=16)
    net = CBFNet(cfg).to(dtype)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return net.eval()


@given(g=gst.elements(GROUP, batch=(2,)), seed=st.integers(0, 2**20))
@settings(max_examples=10, deadline=None)
def test_learned_barrier_is_invariant(g, seed):
    """EGCBF+'s h is SE2xR invariant: float64 within 1e-9, float32 within 1e-5."""
    state, cfg = _scene(seed)
    for dtype, tol in ((F64, 1e-9), (torch.float32, 1e-5)):
        bar = LearnedBarrier(_cbf(dtype), 1.0)
        a, b = bar.values(state, cfg), bar.values(state.transform(g), cfg)
        assert a.dtype == F64 and a.shape == (2, 6)
        assert (a - b).abs().max() <= tol


def test_learned_barrier_needs_a_positive_gain():
    with pytest.raises(ValueError, match="alpha"):
        LearnedBarrier(_cbf(), 0.0)


# ---------------------------------------------------------------------------------------------------- rollouts
def _small(num_agents=8, obstacles=2, steps=24):
    return EnvConfig(num_agents=num_agents, area_size=1.0, num_obstacles=obstacles, max_steps=steps)


def test_rollout_collisions_are_the_evaluations():
    cfg = _small()
    ctrl = make_controller("nominal")
    seeds = [11, 12]
    traj = roll_out(ctrl, {"dcbf": BrakingBarrier(DCBF_FILTER_BARRIER)}, cfg, seeds)
    stats, _, _ = run_episodes(ctrl, cfg, seeds)
    assert traj.collision.shape == (25, 2, 8) and traj.h["dcbf"].shape == (25, 2, 8) and traj.filter_bad is None
    assert torch.equal(traj.collision.any(0), stats.ever_collided.cpu())
    assert not traj.collision[0].any()


def test_rollout_records_the_filters_per_agent_status():
    cfg = _small(steps=12)
    ctrl = FilteredController(None, None, FilterConfig.for_kind("dcbf"))
    seen = []

    def spy(state, env_config):
        u, info = ctrl(state, env_config)
        assert info["slack_mask"].shape == (1, 8) and int(info["slack_mask"].sum()) == info["num_slack"]
        assert int(info["failed_mask"].sum()) == info["num_failed"]
        seen.append(info["slack_mask"] | info["failed_mask"])
        return u, info

    traj = roll_out(spy, {}, cfg, [3])
    assert traj.filter_bad.shape == (12, 1, 8)
    assert torch.equal(traj.filter_bad, torch.from_numpy(np.stack(seen)))
    with pytest.raises(ValueError, match="at least one"):
        roll_out(ctrl, {}, cfg, [])


# ------------------------------------------------------------------------------------------- sweep, report, CLI
def _tiny(tmp_path, **kw):
    base = dict(quadrotor_sizes=((8, 1.0, 1),), quadrotor_seeds=(0,), suite=(), obstacles=(0,),
                out=tmp_path / "cells", workers=1, only="egcbf+-s0 policy:cbf")  # fmt: skip
    base.update(kw)
    return CertifyConfig(**base)


def test_sweep_resumes_and_refuses_stale_cells(tmp_path):
    ckpts = tmp_path / "ckpts"
    shutil.copytree(ROOT / "checkpoints" / "egcbf+", ckpts / "egcbf+")
    cfg = _tiny(tmp_path, checkpoints=ckpts)
    assert [c.name for c in cfg.cells()] == ["quadrotor egcbf+-s0 policy:cbf N 8 obstacles 0"]
    assert sweep(cfg, log=lambda s: None) == {}
    ((_, stored),) = load_cells(cfg)
    assert set(stored["barriers"]) == {"egcbf+-s0", "dcbf"} and stored["barriers"]["egcbf+-s0"]["states"] == 8 * 64
    assert stored["barriers"]["egcbf+-s0"]["filter_states"] == 8 * 64
    assert pending(cfg) == []
    assert pending(dataclasses.replace(cfg, stride=8))  # other settings: to recompute
    report = write_report(cfg, tmp_path / "cert.md", tmp_path / "figs")
    text = report.read_text()
    assert "1 of 1 cells computed" in text and "`egcbf+-s0`" in text and (tmp_path / "figs").exists()
    # a changed checkpoint makes the cell stale: the report refuses it, the sweep recomputes it
    (ckpts / "egcbf+" / "model.safetensors").write_bytes(b"x" + (ckpts / "egcbf+" / "model.safetensors").read_bytes())
    with pytest.raises(ValueError, match="stale"):
        load_cells(cfg)
    assert len(pending(cfg)) == 1


def test_cli_plan_errors_and_narrowed_report(tmp_path):
    runner = CliRunner()
    res = runner.invoke(app, ["certify", "--plan", "--only", "dubins_car egcbf+-s0 policy N 64 obstacles 0"])
    assert res.exit_code == 0, res.output
    assert "dubins_car egcbf+-s0 policy N 64 obstacles 0" in res.output and "cells stored" in res.output
    res = runner.invoke(app, ["certify", "--window", "0"])
    assert res.exit_code == 2 and "--window" in res.output
    res = runner.invoke(app, ["certify", "--only", "no such cell", "--plan"])
    assert res.exit_code == 2 and "selects no cell" in res.output
    res = runner.invoke(app, ["certify", "--report-only", "--stride", "8"])
    assert res.exit_code == 2 and "not the whole plan" in res.output


def test_committed_report_is_what_report_only_writes(tmp_path):
    """docs/certificate.md regenerates identically from the committed cells (and its figure is drawn)."""
    committed = ROOT / "docs" / "certificate.md"
    if not committed.exists():
        pytest.skip("no committed certificate report")
    cfg = CertifyConfig(checkpoints=ROOT / "checkpoints", out=ROOT / "docs" / "results" / "certificate")
    shutil.copy(ROOT / "README.md", tmp_path / "README.md")  # the report quotes its headline into the README
    out = write_report(cfg, tmp_path / "docs" / "certificate.md", tmp_path / "docs" / "figures")
    assert (tmp_path / "README.md").read_text() == (ROOT / "README.md").read_text()
    expected = committed.read_text().replace("`" + str(ROOT / "docs" / "results" / "certificate") + "`", "")
    got = out.read_text().replace("`" + str(cfg.out) + "`", "")
    assert got == expected.replace("`docs/results/certificate`", "")
    assert json.loads((cfg.out / load_cells(cfg)[0][0].filename).read_text())["key"]["seed"] == 0
