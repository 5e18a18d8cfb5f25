"""The learning algorithm: labels, buffers, the CBF Jacobian, the QP target, the loss and the learner's update."""

import functools

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.algo import (
    GraphCBFLearner,
    Samples,
    TrajectoryBuffer,
    UnsafeBuffer,
    cbf_jacobian,
    cbf_loss,
    finite_horizon_labels,
    make_interface,
    solve_cbf_qp,
)
from egcbf.algo.config import LEARNED_METHODS, TrainConfig
from egcbf.env import EnvConfig, SwarmEnv, SwarmState
from egcbf.env.graph import build_graph, refresh_graph
from egcbf.nn import CBFNet, ModelConfig
from egcbf.robots.quadrotor import dynamics as dyn
from egcbf.robots.quadrotor.so3 import so3_exp

F64 = torch.float64


# ------------------------------------------------------------------------------------------------ labels
def test_labels_hand_example():
    # one agent, horizon 2: unsafe at t = 4 -> t = 2, 3 unlabelled, 4 unsafe; the rest safe (the end is cut)
    u = torch.tensor([0, 0, 0, 0, 1, 0, 0], dtype=torch.bool)[:, None]
    safe, unsafe = finite_horizon_labels(u, 2)
    assert safe[:, 0].tolist() == [True, True, False, False, False, True, True]
    assert torch.equal(unsafe, u)
    safe, _ = finite_horizon_labels(u, 2, truncated_safe=False)  # windows cut by the end stay unlabelled
    assert safe[:, 0].tolist() == [True, True, False, False, False, False, False]
    safe, _ = finite_horizon_labels(u, 0)
    assert torch.equal(safe, ~u)


@given(seed=st.integers(0, 2**20), horizon=st.integers(0, 6), length=st.integers(1, 20))
@settings(max_examples=25)
def test_labels_match_the_definition(seed, horizon, length):
    u = torch.rand(length, 2, 3, generator=torch.Generator().manual_seed(seed)) < 0.15
    safe, unsafe = finite_horizon_labels(u, horizon)
    assert not (safe & unsafe).any()
    for t in range(length):
        assert torch.equal(safe[t], ~u[t : t + horizon + 1].any(0))


# ------------------------------------------------------------------------------------------------ buffers
def _samples(lead: tuple[int, ...], n: int = 3, k: int = 2, hits: int = 4, value: float = 0.0) -> Samples:
    return Samples(
        x=torch.full((*lead, n, 18), value),
        goals=torch.zeros(*lead, n, 3),
        centers=torch.zeros(*lead, k, 3),
        radii=torch.ones(*lead, k),
        boxes=torch.zeros(*lead, k, 0),
        hit_points=torch.zeros(*lead, n, hits, 3),
        hit_valid=torch.zeros(*lead, n, hits, dtype=torch.bool),
        safe=torch.ones(*lead, n, dtype=torch.bool),
        unsafe=torch.zeros(*lead, n, dtype=torch.bool),
    )


def test_trajectory_buffer_is_a_ring_and_serializes():
    buf = TrajectoryBuffer(3)
    gen = torch.Generator().manual_seed(0)
    assert buf.sample(2, gen) is None
    for v in range(5):  # 5 trajectories of 4 steps into a ring of 3
        buf.append(_samples((1, 4), value=float(v)))
    assert len(buf) == 3
    got = sorted(float(s) for s in buf.sample(10, gen).x[:, 0, 0, 0])
    assert got == [2.0, 3.0, 4.0]  # distinct, the most recent
    other = TrajectoryBuffer(3)
    other.load_state_dict(buf.state_dict())
    assert len(other) == 3 and torch.equal(other.data.x, buf.data.x) and other.ptr == buf.ptr
    with pytest.raises(ValueError):
        TrajectoryBuffer(4).load_state_dict(buf.state_dict())


def test_unsafe_buffer_keeps_unsafe_graphs_and_handles_empty():
    buf = UnsafeBuffer(4)
    gen = torch.Generator().manual_seed(0)
    assert buf.sample(8, gen) is None  # empty: no crash (GCBF+ users hit one)
    s = _samples((6,))
    assert buf.add(s) == 0 and len(buf) == 0
    s.unsafe[1, 2] = s.unsafe[4, 0] = True
    s.x[1], s.x[4] = 1.0, 2.0
    assert buf.add(s) == 2
    drawn = buf.sample(50, gen)  # oversampled with replacement
    assert len(drawn) == 50 and set(drawn.x[:, 0, 0].tolist()) == {1.0, 2.0}
    empty = UnsafeBuffer(4)
    empty.load_state_dict(UnsafeBuffer(4).state_dict())
    assert len(empty) == 0 and empty.sample(3, gen) is None


# ---------------------------------------------------------------------------------------------- scenes
def _scene(cfg: EnvConfig, seed: int, speed: float = 1.0) -> SwarmState:
    s = SwarmEnv(cfg, dtype=F64).reset(seed)
    gen = torch.Generator().manual_seed(seed + 1)
    b, n = cfg.num_envs, cfg.num_agents
    rot = so3_exp(0.3 * torch.randn(b, n, 3, generator=gen, dtype=F64))
    v = speed * torch.randn(b, n, 3, generator=gen, dtype=F64)
    w = torch.randn(b, n, 3, generator=gen, dtype=F64)
    return SwarmState(dyn.state_from_parts(s.positions, rot, v, w), s.goals, s.obstacles)


@functools.cache
def _cbf(group: str, bias: float = 0.0) -> CBFNet:
    torch.manual_seed(1)
    net = CBFNet(ModelConfig(group=group, hidden=32, heads=4, head_hidden=32)).double()
    with torch.no_grad():
        net.head[-1].bias.fill_(bias)  # shift h so that many CBF constraints are active
    return net


_CFG = EnvConfig(num_agents=5, num_envs=3, area_size=1.2, num_obstacles=2, n_rays=8, lidar_max_hits=4)


@pytest.mark.parametrize("group", ["se2xr", "trivial"])
def test_cbf_jacobian_matches_one_backward_per_agent(group):
    net = _cbf(group)
    state = _scene(_CFG, 4)
    graph = build_graph(state, _CFG)
    h, jac = cbf_jacobian(net, graph, state.x)
    b, n = state.x.shape[:2]
    x = state.x.clone().requires_grad_(True)
    hh = net(refresh_graph(graph, x)).view(b, n)
    ref = torch.stack([torch.autograd.grad(hh[:, i].sum(), x, retain_graph=True)[0] for i in range(n)], 1)
    assert torch.allclose(h, hh.detach(), atol=1e-12, rtol=0)
    assert torch.allclose(jac, ref, atol=1e-12, rtol=0)
    assert all(p.grad is None for p in net.parameters())


# ------------------------------------------------------------------------------------------------ QP target
INTERFACES = ["torque", "accel"]


def _qp(group: str, state: SwarmState, interface: str = "torque", alpha: float = 0.1, lg_scale: float = 1.0):
    """The learned-CBF QP of ``state`` over the commands of ``interface``, as the learner builds it: returns
    ``h, lf, lg, c_ref`` (the last two in the local coordinates of the box), ``lo, hi`` and the result."""
    net = _cbf(group, bias=-0.6)
    graph = build_graph(state, _CFG)
    itf = make_interface(interface)
    h, lf, lg = itf.lie_derivatives(net, graph, state.x)
    lg = lg_scale * itf.to_local(state.x[:, None], lg)
    c_ref = itf.to_local(state.x, itf.nominal(state.x, state.goals))
    lo, hi = itf.bounds(h)
    return h, lf, lg, c_ref, lo, hi, solve_cbf_qp(h, lf, lg, c_ref, lo, hi, alpha=alpha)


@pytest.mark.parametrize("interface", INTERFACES)
@given(seed=st.integers(0, 2**16))
@settings(max_examples=8)
def test_qp_target_satisfies_the_learned_cbf_constraints_up_to_its_slack(interface, seed):
    state = _scene(_CFG, seed, speed=2.0)
    h, lf, lg, _, lo, hi, res = _qp("se2xr", state, interface)
    assert res.converged.all()
    assert (res.u >= lo - 1e-9).all() and (res.u <= hi + 1e-9).all() and (res.slack >= 0).all()
    # the constraint, recomputed independently from the Lie derivatives
    resid = lf + torch.einsum("bijk,bjk->bi", lg, res.u) + 0.1 * h
    assert torch.allclose(resid, res.residual, atol=1e-9)
    scale = 1 + lf.abs().amax() + lg.abs().amax()
    assert (resid + res.slack >= -1e-6 * scale).all()
    stats = res.stats()
    assert stats["num_slack"] == int((res.slack > 1e-6).sum()) and stats["num_failed"] == 0
    assert stats["num_constraints"] == h.numel()
    # a CBF almost insensitive to the control: the constraints cannot all be met, the slack takes the rest
    h, lf, lg, _, _, _, weak = _qp("se2xr", state, interface, lg_scale=1e-4)
    assert weak.converged.all() and weak.stats()["num_slack"] > 0
    resid = lf + torch.einsum("bijk,bjk->bi", lg, weak.u) + 0.1 * h
    assert (resid + weak.slack >= -1e-6 * scale).all()


@pytest.mark.parametrize("interface", INTERFACES)
def test_qp_target_is_optimal_and_active(interface):
    proxsuite = pytest.importorskip("proxsuite")
    state = _scene(_CFG, 11, speed=2.0)
    h, lf, lg, c_ref, lo, hi, res = _qp("trivial", state, interface)
    c_ref = torch.maximum(torch.minimum(c_ref, hi), lo)
    moved = (res.u - c_ref).abs().amax((-1, -2)) > 1e-3
    assert moved.any()  # some constraints are active: the target differs from the nominal command
    b, n, k = c_ref.shape
    nu = k * n
    for e in range(b):
        a = lg[e].reshape(n, nu).numpy()
        H = np.diag(np.r_[np.ones(nu), np.full(n, 10.0)])
        g = np.r_[-c_ref[e].reshape(-1).numpy(), np.full(n, 1e3)]
        C = np.c_[a, np.eye(n)]  # a u + s >= -(Lf h + alpha h)
        qp = proxsuite.proxqp.dense.QP(nu + n, 0, n, True)
        qp.settings.eps_abs = 1e-10
        rhs = -(lf[e] + 0.1 * h[e]).numpy()
        box_lo, box_hi = np.r_[lo.repeat(n).numpy(), np.zeros(n)], np.r_[hi.repeat(n).numpy(), np.full(n, 1e20)]
        qp.init(H, g, None, None, C, rhs, np.full(n, 1e20), box_lo, box_hi)
        qp.solve()
        assert np.abs(qp.results.x[:nu] - res.u[e].reshape(-1).numpy()).max() < 1e-3
        assert np.abs(qp.results.x[nu:] - res.slack[e].numpy()).max() < 1e-4


@pytest.mark.parametrize("interface", INTERFACES)
def test_qp_target_of_an_invariant_cbf_is_invariant(interface):
    """In local coordinates (torques; accelerations in each agent's yaw frame) the QP of an invariant CBF is the
    same QP in a transformed scene, so its solution is invariant (and the world-frame command rotates)."""
    state = _scene(_CFG, 5, speed=2.0)
    g = torch.tensor([[0.6, 0.8, 0.4, -0.3, 0.2], [0.0, -1.0, 1.0, 2.0, -1.0], [-1.0, 0.0, 0.0, 0.0, 3.0]], dtype=F64)
    *_, r1 = _qp("se2xr", state, interface)
    *_, r2 = _qp("se2xr", state.transform(g), interface)
    assert (r1.u - r2.u).abs().max() < 1e-8 and (r1.slack - r2.slack).abs().max() < 1e-8


# ------------------------------------------------------------------------------------------------ loss
def _loss_inputs():
    h = torch.tensor([0.01, 0.05, -0.2, 0.3])
    h_next = torch.tensor([0.0, 0.06, -0.25, 0.31])
    safe = torch.tensor([True, False, False, False])
    unsafe = torch.tensor([False, True, False, False])
    u = torch.zeros(4, 4)
    u_ref = torch.tensor([[0.1, 0, 0, 0], [0, 0.2, 0, -0.1], [0, 0, 0, 0], [0.3, 0.4, 0, 0]])
    return h, h_next, safe, unsafe, u, u_ref


def test_loss_terms_hand_computed():
    h, h_next, safe, unsafe, u, u_ref = _loss_inputs()
    out = cbf_loss(h, h_next, safe, unsafe, u, u_ref, 0.1, gamma=0.02, alpha=1.0, eta_d=0.2, eta_c=0.5)
    # unsafe: relu(0.02 + 0.05) = 0.07;  safe: relu(0.02 - 0.01) = 0.01
    # hdot = (h' - h) / 0.1 = (-0.1, 0.1, -0.5, 0.1); relu(0.02 - hdot - h) = (0.11, 0, 0.72, 0) -> mean 0.2075
    # ||u - u_ref||^2 = (0.01, 0.05, 0, 0.25) -> mean 0.0775
    expected = {"unsafe": 0.07, "safe": 0.01, "hdot": 0.2075, "control": 0.0775,
                "total": 0.07 + 0.01 + 0.2 * 0.2075 + 0.5 * 0.0775,
                "acc_unsafe": 0.0, "acc_safe": 1.0, "acc_hdot": 0.5}  # fmt: skip
    for k, v in expected.items():
        assert float(out[k]) == pytest.approx(v, abs=1e-6), k
    norm = cbf_loss(h, h_next, safe, unsafe, u, u_ref, 0.1, control="norm")
    assert float(norm["control"]) == pytest.approx((0.1 + 0.05**0.5 + 0.0 + 0.5) / 4, abs=1e-6)
    none = cbf_loss(h, h_next, torch.zeros(4, dtype=torch.bool), torch.zeros(4, dtype=torch.bool), u, u_ref, 0.1)
    assert float(none["safe"]) == 0.0 and float(none["unsafe"]) == 0.0  # empty label sets: 0, not nan


def test_loss_unlabelled_agents_train_only_the_action():
    h, h_next, safe, unsafe, u, u_ref = _loss_inputs()
    h, h_next, frozen = h.clone().requires_grad_(), h_next.clone().requires_grad_(), h_next.clone().requires_grad_()
    out = cbf_loss(h, h_next, safe, unsafe, u, u_ref, 0.1, h_next_frozen=frozen)
    assert float(out["hdot"]) == pytest.approx(0.2075, abs=1e-6)  # same value
    out["total"].backward()
    # agent 2 is unlabelled and violates the condition: only the frozen path (to the action) gets its gradient
    assert h.grad[2] == 0 and h_next.grad[2] == 0
    assert frozen.grad[2] == pytest.approx(-0.2 / 4 / 0.1)
    assert h_next.grad[0] == pytest.approx(-0.2 / 4 / 0.1) and frozen.grad[0] == 0  # labelled: the CBF learns


def test_the_condition_accuracy_reads_each_agent_where_its_loss_does():
    """acc_hdot counts an agent whose derivative term does not train the CBF with the frozen CBF's values (its
    full-graph next value), not with h_next (which the learner reads on a graph without that agent's neighbours)."""
    h, h_next, safe, unsafe, u, u_ref = _loss_inputs()
    masked_graph = torch.full_like(h_next, 10.0)  # "nothing in range": the condition would always look met
    frozen = h - 1.0  # the true next values: the condition fails everywhere
    none = torch.zeros_like(safe)
    out = cbf_loss(h, masked_graph, safe, unsafe, u, u_ref, 0.1, h_next_frozen=frozen, hdot_labelled=none)
    assert float(out["acc_hdot"]) == 0.0
    out = cbf_loss(h, masked_graph, safe, unsafe, u, u_ref, 0.1, h_next_frozen=frozen, hdot_labelled=~none)
    assert float(out["acc_hdot"]) == 1.0  # agents that train the CBF are read on their own (full) graph


# ------------------------------------------------------------------------------------------------ learner
def test_update_with_no_unsafe_data_and_gradient_routing():
    learner = GraphCBFLearner(TrainConfig.preset("egcbf+", "tiny"))
    roll = learner.collect(0)
    assert len(learner.unsafe_buffer) == 0
    data = learner.assemble(roll)  # empty unsafe buffer: just the rollout
    assert len(data) == roll.x.shape[0] * roll.x.shape[1]
    # all unlabelled: the CBF gets no gradient at all, the policy does
    data.safe[:] = False
    data.unsafe[:] = False
    u_ref, _ = learner.reference(data)
    terms = learner.loss(data, u_ref)
    terms["total"].backward()
    assert all(p.grad is None or not p.grad.any() for p in learner.cbf.parameters())
    assert any(p.grad is not None and p.grad.any() for p in learner.policy.parameters())


def test_derivative_term_can_train_the_policy_only():
    """``hdot_trains_cbf=False``: with the label terms off, labelled agents' derivative term reaches the policy and
    not the CBF; with it on, the CBF learns from it too."""
    for trains_cbf in (True, False):
        cfg = TrainConfig.preset("egcbf+", "tiny", eta_safe=0.0, eta_unsafe=0.0, eta_c=0.0, eta_d=1.0, gamma=5.0,
                                 hdot_trains_cbf=trains_cbf)  # fmt: skip
        learner = GraphCBFLearner(cfg)
        data = learner.assemble(learner.collect(0))
        data.safe[:] = True  # every agent labelled; gamma = 5 makes every derivative term active
        data.unsafe[:] = False
        u_ref, _ = learner.reference(data)
        learner.loss(data, u_ref)["total"].backward()
        cbf_grad = any(p.grad is not None and p.grad.any() for p in learner.cbf.parameters())
        assert cbf_grad == trains_cbf
        assert any(p.grad is not None and p.grad.any() for p in learner.policy.parameters())


@pytest.mark.parametrize("algo", sorted(LEARNED_METHODS))
def test_training_decreases_the_loss_on_a_fixed_batch(algo):
    cfg = TrainConfig.preset(algo, "tiny", lr_cbf=3e-3, lr_policy=3e-3)
    learner = GraphCBFLearner(cfg)
    data = learner.assemble(learner.collect(0))
    data.unsafe[::5, 0] = True  # make every term of the loss present
    data.safe &= ~data.unsafe
    u_ref, qp = learner.reference(data)
    assert (cfg.reference == "qp") == bool(qp)
    losses = [learner.train_step(data, u_ref)["total"] for _ in range(25)]
    assert sum(losses[-3:]) / 3 < 0.7 * sum(losses[:3]) / 3, losses


@pytest.mark.parametrize("interface", INTERFACES)
@pytest.mark.parametrize("group", ["se2xr", "trivial"])
def test_qp_target_with_two_agents_at_the_same_point_is_finite(interface, group):
    """Coincident agents (``dp = 0``, where ``|dp|`` has no derivative): the learned CBF, its Jacobian and the QP's
    commands stay finite and the QP converges (the edge encoder's ``|dp|`` has the zero subgradient there)."""
    state = _scene(_CFG, 4)
    x = state.x.clone()
    x[:, 1] = x[:, 0]  # agent 1 exactly on agent 0, same attitude, velocity and body rates
    state = SwarmState(x, state.goals, state.obstacles)
    h, lf, lg, *_, res = _qp(group, state, interface)
    for name, t in (("h", h), ("lf", lf), ("lg", lg), ("u", res.u), ("slack", res.slack)):
        assert torch.isfinite(t).all(), name
    assert bool(res.converged.all())
    assert (res.residual >= -res.slack - 1e-6).all()
