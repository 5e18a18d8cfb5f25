"""The per-edge QP target (``TrainConfig.qp_constraints = "edges"``, :mod:`egcbf.algo.edge_qp`): it is exactly the
nominal command behind the learned-CBF run-time filter (the controller the docs measure as a teacher), that
controller is SE2xR-equivariant (hypothesis, float64 within 1e-7 m/s^2, as the filters' tests), every agent's
target keeps its rows and its box, and a run with it trains end to end."""

import functools

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.algo import GraphCBFLearner
from egcbf.algo.config import TrainConfig
from egcbf.algo.edge_qp import edge_rows
from egcbf.control.filters import FilterConfig, FilteredController
from egcbf.env.graph import GROUP
from egcbf.robots.quadrotor.barriers import AccelBounds, bound_rows
from egcbf.train.loop import train
from groupcanon import FieldType
from groupcanon.features import Vector
from groupcanon.testing import strategies as gst

F64 = torch.float64


@functools.cache
def _learner_and_data():
    """A tiny EGCBF+ learner with the per-edge target, its CBF moved off the prior, and one labelled rollout."""
    cfg = TrainConfig.preset("egcbf+", "tiny", qp_constraints="edges", num_agents=5, area_size=1.0, dtype="float64")
    learner = GraphCBFLearner(cfg)
    torch.manual_seed(1)
    with torch.no_grad():
        for p in learner.cbf_target.parameters():
            p.add_(0.05 * torch.randn_like(p))
    data = learner.collect(3).flatten()
    return learner, data


def test_the_target_is_the_nominal_command_behind_the_learned_cbf_filter():
    learner, data = _learner_and_data()
    cfg, itf = learner.config, learner.interface
    c_ref, stats = learner.reference(data)
    assert c_ref.shape == (len(data), cfg.num_agents, 3) and stats["num_failed"] == 0
    ctrl = FilteredController(
        None, cfg.model, FilterConfig(kind="cbf", alpha=cfg.qp_edge_alpha, qp_solver="ipm"), learner.cbf_target
    )  # the target's own solver
    state = data.state(learner.robot)
    _, info = ctrl(state, learner.env_config)
    assert (info["a_safe"] / itf.accel_unit - c_ref).abs().max() <= 1e-9
    # and it is a correction: some agents' targets differ from their nominal commands, most do not
    c_nom = itf.nominal(data.x, data.goals)
    moved = (c_ref - c_nom).norm(dim=-1) > 1e-6
    assert 0 < int(moved.sum()) < moved.numel()


def test_every_target_keeps_its_rows_and_its_box():
    """Each agent's target satisfies each of its per-edge rows (up to its slack: the rows can conflict with the
    box) and the yaw-frame box; an agent whose nominal command already satisfies all its rows keeps it."""
    learner, data = _learner_and_data()
    cfg, itf, mc = learner.config, learner.interface, learner.config.model
    c_ref, _ = learner.reference(data)
    a = (itf.accel_unit * c_ref).reshape(-1, 3).to(F64)
    a_nom = (itf.accel_unit * itf.nominal(data.x, data.goals)).reshape(-1, 3).to(F64)
    rows = edge_rows(data.graph(learner.env_config), cfg.qp_edge_alpha, 0.0, learner.cbf_target, mc.cbf_distance,
                     mc.closest_approach_horizon)  # fmt: skip
    lhs = (rows.normal * a[rows.owner]).sum(-1)
    short = (rows.rhs - lhs).clamp(min=0)
    slack = torch.zeros(a.shape[0], dtype=F64).scatter_reduce_(0, rows.owner, short, "amax")
    assert float(slack.max()) < 30.0  # bounded by the box
    nominal_ok = torch.ones(a.shape[0], dtype=torch.bool)
    nominal_ok[rows.owner[(rows.normal * a_nom[rows.owner]).sum(-1) < rows.rhs - 1e-9]] = False
    box = AccelBounds(itf.horizontal, -itf.down, itf.up, polygon=2)
    bC, blo, bhi = bound_rows(data.x[..., 3:12].reshape(-1, 9).to(F64).numpy(), box)
    in_box = np.all((np.einsum("mkj,mj->mk", bC, a_nom.numpy()) >= blo - 1e-9)
                    & (np.einsum("mkj,mj->mk", bC, a_nom.numpy()) <= bhi + 1e-9), axis=1)  # fmt: skip
    keep = nominal_ok & torch.as_tensor(in_box)
    assert bool(keep.any())
    assert (a[keep] - a_nom[keep]).abs().max() <= 1e-6
    ca = np.einsum("mkj,mj->mk", bC, a.numpy())
    assert np.all(ca >= blo - 1e-6) and np.all(ca <= bhi + 1e-6)


@given(g=gst.elements(GROUP, batch=(1,)), index=st.integers(0, 23))
@settings(max_examples=10, deadline=None)
def test_the_target_is_equivariant(g, index):
    """Transforming a training sample by SE2xR rotates its target (float64, 1e-7 m/s^2)."""
    learner, data = _learner_and_data()
    assert len(data) == 24  # 2 environments x 12 steps
    cfg = learner.config
    state = data[index : index + 1].state(learner.robot)
    ctrl = FilteredController(
        None, cfg.model, FilterConfig(kind="cbf", alpha=cfg.qp_edge_alpha, qp_solver="ipm"), learner.cbf_target
    )  # the target's own solver
    _, a = ctrl(state, learner.env_config)
    _, b = ctrl(state.transform(g), learner.env_config)
    rotate = FieldType(GROUP, [Vector(3)])
    ga = g[:, None].expand(1, cfg.num_agents, 5)
    assert (rotate.act(ga, a["a_safe"]) - b["a_safe"]).abs().max() <= 1e-7


def test_the_config_refuses_edges_without_the_soft_min_head():
    with pytest.raises(ValueError, match="qp_constraints must be 'cbf' or 'edges'"):
        TrainConfig.preset("egcbf+", "tiny", qp_constraints="pairs")
    with pytest.raises(ValueError, match="soft-min CBF head"):
        TrainConfig.preset("egcbf+", "tiny", qp_constraints="edges", model={"cbf_head": "mlp"})
    with pytest.raises(ValueError, match="qp_edge_alpha"):
        TrainConfig.preset("egcbf+", "tiny", qp_edge_alpha=0.0)
    assert TrainConfig.preset("egcbf+", "cpu").qp_constraints == "cbf"  # the paper's target stays the default


def test_a_run_with_the_per_edge_target_trains(tmp_path):
    cfg = TrainConfig.preset("gcbf+", "tiny", steps=2, qp_constraints="edges")
    learner = train(cfg, tmp_path, progress=False, log=lambda s: None)
    assert learner.step == 2
    saved = TrainConfig.from_json(tmp_path / "config.json")
    assert saved.qp_constraints == "edges"
    tags = (tmp_path / "scalars.csv").read_text()
    assert "qp/num_slack" in tags and "qp/rows_dropped" in tags
