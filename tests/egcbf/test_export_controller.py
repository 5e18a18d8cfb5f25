"""``egcbf export --controller METHOD:dcbf``: the exported filtered controller (egcbf.deploy.controller_export) and
its standalone runtime (egcbf.deploy.runtime) compute what egcbf.deploy.agent.AgentFilteredController computes.

float64, the filter part fed the PyTorch policy's command: rows, box, attitude loop and fallback within 1e-9 of the
PyTorch filter's; the QP solved exactly (a KKT certificate on every scene, and against an enumeration of active
sets on random QPs); the command within 1e-9 of the PyTorch filter's wherever that filter's own solve is exact
(QP inactive), and within its interior-point accuracy (``IPM_TOL``) where its polishing step is refused. float32, the
whole exported directory (ONNX policy + runtime) against the PyTorch controller: ``F32_TOL``. The runtime runs in a
fresh interpreter that never imports torch, egcbf or groupcanon; bad directories and inputs are named."""

from __future__ import annotations

import functools
import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from egcbf.cli import app
from egcbf.deploy import runtime
from egcbf.deploy.agent import AgentFilteredController
from egcbf.deploy.controller_export import controller_settings, load_runtime
from egcbf.env import EnvConfig, SwarmEnv

onnxruntime = pytest.importorskip("onnxruntime")
ROOT = Path(__file__).resolve().parents[2] / "checkpoints"
F64 = torch.float64
MAX_NEIGHBOURS, MAX_HITS = 8, 16
EXACT = 1e-9
#: the PyTorch filter's QP where a CBF row is active at zero slack: its interior-point iterate (the polishing step
#: refuses the slack row's multiplier, ~w1 = 1e3), accurate to ~1e-6 m/s^2 (command units: / 5 m/s^2)
IPM_TOL = 1e-5
#: float32 ONNX policy against the PyTorch float32 policy, through the filter and the attitude loop
F32_TOL = 1e-5


@functools.cache
def _filtered(method: str, dtype: torch.dtype = F64, max_neighbours: int = 64, max_hits: int | None = None):
    """The swarm's filtered controller, its training config, the per-agent one (``max_neighbours`` and ``max_hits``
    rows: the defaults hold every neighbour and hit of the scenes here, as the swarm's has no limit) and the
    runtime around the latter's settings."""
    from egcbf.control.resolve import resolve

    built = resolve(f"{method}:dcbf", ROOT / method, dtype=dtype)
    agent = AgentFilteredController.from_checkpoint(ROOT / method, dtype=dtype, max_neighbours=max_neighbours,
                                                    max_hits=max_hits)  # fmt: skip
    return built.controller, built.train_config, agent, runtime.Controller(controller_settings(agent), None)


def _scene(cfg, n: int, area: float, obstacles: int, seed: int, dtype=F64):
    """A moving scene, the swarm filter's control of it and the realized accelerations of its last step."""
    swarm = _filtered(cfg.algo, dtype)[0]
    env_cfg = EnvConfig.for_robot(cfg.robot, num_agents=n, area_size=area, num_obstacles=obstacles, num_envs=1,
                                  **cfg.env_overrides)  # fmt: skip
    env = SwarmEnv(env_cfg, dtype=dtype)
    state = env.reset(seed)
    for _ in range(5):
        state, _ = env.step(state, swarm(state, env_cfg)[0])
    v_prev = state.x[0, :, 12:15].clone()
    state, _ = env.step(state, swarm(state, env_cfg)[0])
    u_all, _ = swarm(state, env_cfg)
    acc = (state.x[0, :, 12:15] - v_prev) / env_cfg.dt
    return env, state, u_all, acc


def _agents(env, state, acc):
    """Every agent's observation: ``(state, goal, others, hits, accelerations in the call's order, obstacles)``."""
    lidar = env.lidar(state)
    n = state.x.shape[1]
    obstacles = (state.obstacles.centers[0], state.obstacles.radii[0])
    for i in range(n):
        order = torch.tensor([i] + [j for j in range(n) if j != i])
        others = state.x[0, order[1:]]
        yield i, state.x[0, i], state.goals[0, i], others, lidar.points[0, i][lidar.valid[0, i]], acc[order], obstacles


def _qp(rt: runtime.Controller, x: np.ndarray, acc: np.ndarray, command: np.ndarray, obstacles):
    """The runtime's QP of agent ``x[0]`` as ``(M, b, H, g)``: rows ``M z >= b``, cost ``z'Hz / 2 + g'z``."""
    s = rt.settings["filter"]
    t = s["lookahead"]
    p, v = x[:, :3] + t * x[:, 12:15] + 0.5 * t**2 * acc, x[:, 12:15] + t * acc
    normal, rhs = runtime.agent_rows(p[0], v[0], p[1:], v[1:], *obstacles, s)
    C, lo, hi = runtime.bound_rows(x[0, 3:12], s["bounds"])
    M = np.zeros((len(rhs) + 2 * len(lo) + 1, 4))
    M[: len(rhs), :3], M[: len(rhs), 3] = normal, 1.0
    M[len(rhs) : len(rhs) + len(lo), :3], M[len(rhs) + len(lo) : -1, :3], M[-1, 3] = C, -C, 1.0
    w1, w2 = s["penalty"]["w1"], s["penalty"]["w2"]
    g = np.concatenate((-rt.command_unit * command, [w1]))
    return M, np.concatenate((rhs, lo, -hi, [0.0])), np.diag([1.0, 1.0, 1.0, w2]), g


def _kkt_error(z: np.ndarray, M, b, H, g) -> float:
    """How far ``z`` is from the QP's optimum: primal infeasibility, and the stationarity residual and negative
    multipliers of the rows active at ``z`` (least squares)."""
    r = M @ z - b
    act = np.abs(r) <= 1e-9 * (1 + np.abs(b))
    lam = np.linalg.lstsq(M[act].T, H @ z + g, rcond=None)[0] if act.any() else np.zeros(0)
    stat = H @ z + g - M[act].T @ lam
    return max(float(-r.min()), float(np.abs(stat).max()) / 1e3, float(-lam.min(initial=0.0)) / 1e3)


@pytest.mark.parametrize("method", ["egcbf+", "gcbf+"])
@given(seed=st.integers(0, 2**16), n=st.integers(2, 12), area=st.floats(0.8, 2.0), obstacles=st.integers(0, 3))
@settings(max_examples=3, deadline=None)
def test_the_filter_is_the_per_agent_and_swarm_filters(method, seed, n, area, obstacles):
    """float64, fed the PyTorch policy's command: the runtime's QP is solved exactly (KKT), and its command and
    control are the per-agent and swarm filters' within 1e-9 where the QP is inactive, within the PyTorch solver's
    accuracy where it is active."""
    _, cfg, agent, rt = _filtered(method)
    env, state, u_all, acc = _scene(cfg, n, area, obstacles, seed)
    for i, x, goal, others, hits, a, obs in _agents(env, state, acc):
        u_ref, ref = agent(x, goal, others, hits, obstacles=obs, accelerations=a)
        command = ref["policy_command"].numpy()
        obs_np = tuple(t.numpy() for t in obs)
        u, info = rt.filter(x.numpy(), command, others.numpy(), accelerations=a.numpy(), obstacles=obs_np)
        assert info["failed"] == ref["failed"]
        xs = torch.cat((x[None], others)).numpy()
        assert _kkt_error(np.append(info["a_safe"], info["slack"]), *_qp(rt, xs, a.numpy(), command, obs_np)) <= EXACT
        tol = EXACT if np.array_equal(info["command"], command) else IPM_TOL
        for want in (u_ref.numpy(), u_all[0, i].numpy()):
            assert np.abs(u - want).max() <= tol, (i, info)
        assert np.abs(info["command"] - ref["command"].numpy()).max() <= tol, (i, info)


def test_a_crowded_scene_exercises_the_qp():
    """12 agents in a 0.9 m cube among 3 obstacles: the filter changes several commands; the runtime's are the
    PyTorch filter's within that filter's solver accuracy."""
    _, cfg, agent, rt = _filtered("egcbf+")
    env, state, _, acc = _scene(cfg, 12, 0.9, 3, 5)
    changed = 0
    for _i, x, goal, others, hits, a, obs in _agents(env, state, acc):
        _, ref = agent(x, goal, others, hits, obstacles=obs, accelerations=a)
        command, obs_np = ref["policy_command"].numpy(), tuple(t.numpy() for t in obs)
        _, info = rt.filter(x.numpy(), command, others.numpy(), accelerations=a.numpy(), obstacles=obs_np)
        changed += not np.array_equal(info["command"], command)
        assert np.abs(info["command"] - ref["command"].numpy()).max() <= IPM_TOL
    assert changed >= 4


def _brute_force(M, b, H, g):
    """The QP's optimum by enumerating active sets of at most 4 rows (the unique KKT point)."""
    for k in range(5):
        for act in itertools.combinations(range(len(b)), k):
            a = M[list(act)]
            kkt = np.block([[H, -a.T], [a, np.zeros((k, k))]])
            if abs(np.linalg.det(kkt)) < 1e-12:
                continue
            sol = np.linalg.solve(kkt, np.concatenate((-g, b[list(act)])))
            if (M @ sol[:4] - b >= -1e-10).all() and (sol[4:] >= -1e-10).all():
                return sol[:4]
    raise AssertionError("no KKT point")


@given(seed=st.integers(0, 2**32 - 1), rows=st.integers(0, 6), yaw=st.floats(-3.2, 3.2))
@settings(max_examples=40, deadline=None)
def test_the_qp_solver_is_exact(seed, rows, yaw):
    """Random CBF rows (unit normals, right-hand sides up to 8 m/s^2) in a turned box: the dual active-set solution
    is the enumerated KKT point within 1e-9."""
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=(rows, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    rhs = rng.uniform(-8.0, 8.0, rows)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).reshape(9)
    bounds = {"horizontal": 3.3, "z_min": -4.9, "z_max": 4.2, "polygon": 4}
    C, lo, hi = runtime.bound_rows(rot, bounds)
    a_ref = rng.uniform(-8.0, 8.0, 3)
    z, ok = runtime.solve_qp(a_ref, normal, rhs, C, lo, hi, 1e3, 1e2)
    M = np.zeros((rows + 2 * len(lo) + 1, 4))
    M[:rows, :3], M[:rows, 3], M[rows : rows + len(lo), :3], M[rows + len(lo) : -1, :3], M[-1, 3] = normal, 1, C, -C, 1
    b = np.concatenate((rhs, lo, -hi, [0.0]))
    want = _brute_force(M, b, np.diag([1.0, 1.0, 1.0, 1e2]), np.concatenate((-a_ref, [1e3])))
    assert ok and np.abs(z - want).max() <= EXACT


def test_rows_box_attitude_loop_and_fallback_are_the_torch_ones(monkeypatch):
    """The runtime's pieces against the library's, float64: the agent's rows and box (as the dCBF-QP splits and
    prunes them), the attitude loop and, with the QP forced to fail in both, the braking fallback, within 1e-9."""
    from egcbf.robots.quadrotor import dcbf_qp
    from egcbf.robots.quadrotor.barriers import bound_rows, build_constraints, split_for_agents
    from egcbf.robots.quadrotor.nominal import track_acceleration

    _, cfg, agent, rt = _filtered("egcbf+")
    env, state, _, acc = _scene(cfg, 9, 0.8, 3, 2)
    barrier, bounds = agent._qp.resolved(agent.env_config)
    s = rt.settings["filter"]
    obstacles = (state.obstacles.centers[0].numpy(), state.obstacles.radii[0].numpy())
    x, a = state.x[0].numpy(), acc.numpy()
    t = s["lookahead"]
    p, v = x[:, :3] + t * x[:, 12:15] + 0.5 * t**2 * a, x[:, 12:15] + t * a
    owner, normal, rhs = split_for_agents(build_constraints(p, v, barrier, *obstacles, bounds=bounds))
    for i in range(x.shape[0]):
        others = [j for j in range(x.shape[0]) if j != i]
        got_n, got_b = runtime.agent_rows(p[i], v[i], p[others], v[others], *obstacles, s)
        want_n, want_b = normal[owner == i], rhs[owner == i]
        assert got_b.shape == want_b.shape
        assert np.abs(np.sort(got_b) - np.sort(want_b)).max(initial=0) <= EXACT
        assert np.abs(got_n[np.argsort(got_b)] - want_n[np.argsort(want_b)]).max(initial=0) <= EXACT
        for got, want in zip(runtime.bound_rows(x[i, 3:12], s["bounds"]), bound_rows(x[i : i + 1, 3:12], bounds)):
            assert np.abs(got - want[0]).max() <= EXACT
        accel = np.random.default_rng(i).normal(scale=6.0, size=3)
        want_u = track_acceleration(state.x[0, i], torch.from_numpy(accel), agent.env_config.params)
        assert np.abs(runtime.track_acceleration(x[i], accel, rt.settings["robot"]) - want_u.numpy()).max() <= EXACT

    def fail(qps, device=None):
        m = len(qps)
        return np.zeros((m, 4)), np.zeros(m, dtype=bool), np.zeros(m, dtype=np.int64)

    monkeypatch.setattr(dcbf_qp, "solve_dense_batch_ipm", fail)
    monkeypatch.setattr(runtime, "solve_qp", lambda *args, **kw: (np.zeros(4), False))
    for _i, xi, goal, others, hits, ai, obs in _agents(env, state, acc):
        u_ref, ref = agent(xi, goal, others, hits, obstacles=obs, accelerations=ai)
        u, info = rt.filter(xi.numpy(), ref["policy_command"].numpy(), others.numpy(), accelerations=ai.numpy(),
                            obstacles=tuple(o.numpy() for o in obs))  # fmt: skip
        assert info["failed"] and ref["failed"]
        assert np.abs(u - u_ref.numpy()).max() <= EXACT
        assert np.abs(info["command"] - ref["command"].numpy()).max() <= EXACT


# ------------------------------------------------------------------------------------------ the exported directory
@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    """egcbf+ behind the dcbf filter, exported by the command line once for the module."""
    out = tmp_path_factory.mktemp("ctrl") / "egcbf+-dcbf"
    args = ["export", "--controller", "egcbf+:dcbf", "--checkpoint", str(ROOT / "egcbf+"), "--out", str(out),
            "--max-neighbours", str(MAX_NEIGHBOURS), "--max-hits", str(MAX_HITS)]  # fmt: skip
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return out


def test_the_directory_holds_its_files(exported):
    assert sorted(p.name for p in exported.iterdir()) == sorted(
        ["policy.onnx", "policy.onnx.json", "controller.json", "egcbf_runtime.py"]
    )
    settings_ = json.loads((exported / "controller.json").read_text())
    assert settings_["format"] == runtime.FORMAT and settings_["name"] == "egcbf+:dcbf"
    assert (
        settings_["policy"]["max_neighbours"] == MAX_NEIGHBOURS and len(settings_["policy"]["checkpoint_sha256"]) == 64
    )
    assert settings_["filter"]["barrier"]["gamma"] == 50.0 and settings_["filter"]["lookahead"] == 0.05
    assert (exported / "egcbf_runtime.py").read_text() == Path(runtime.__file__).read_text()


@given(seed=st.integers(0, 2**16), n=st.integers(1, 12), area=st.floats(0.6, 2.0), obstacles=st.integers(0, 3))
@settings(max_examples=4, deadline=None)
def test_the_whole_export_is_the_pytorch_controller_in_float32(exported, seed, n, area, obstacles):
    """float32 observations: the directory's runtime (ONNX policy, numpy filter) against the PyTorch per-agent
    filtered controller in float32, within F32_TOL, every agent of random scenes."""
    _, cfg, agent, _ = _filtered("egcbf+", torch.float32, MAX_NEIGHBOURS, MAX_HITS)
    rt = load_runtime(exported).Controller.load(exported)
    env, state, _, acc = _scene(cfg, n, area, obstacles, seed, dtype=torch.float32)
    for i, x, goal, others, hits, a, obs in _agents(env, state, acc):
        u_ref, ref = agent(x, goal, others, hits, obstacles=obs, accelerations=a)
        mask = np.ones(others.shape[0], dtype=bool)
        u, info = rt.step(x.numpy(), goal.numpy(), others.numpy(), mask, hits.numpy(), None, a.numpy(),
                          tuple(o.numpy() for o in obs))  # fmt: skip
        assert info["failed"] == ref["failed"] and u.dtype == np.float64
        assert np.abs(u - u_ref.double().numpy()).max() <= F32_TOL, (i, info)
        assert np.abs(info["command"] - ref["command"].double().numpy()).max() <= F32_TOL, (i, info)
        assert info["num_neighbours"] == ref["num_neighbours"] and info["num_hits"] == ref["num_hits"]


def test_the_runtime_runs_without_torch_or_egcbf(exported, tmp_path):
    """A fresh interpreter with the directory on its path: the step imports numpy and onnxruntime only, and gives
    the in-process runtime's output bit for bit."""
    _, cfg, _, _ = _filtered("egcbf+", torch.float32)
    env, state, _, acc = _scene(cfg, 6, 1.0, 2, 9, dtype=torch.float32)
    _, x, goal, others, hits, a, obs = next(_agents(env, state, acc))
    arrays = {"x": x, "goal": goal, "others": others, "hits": hits, "acc": a, "centers": obs[0], "radii": obs[1]}
    np.savez(tmp_path / "in.npz", **{k: t.numpy() for k, t in arrays.items()})
    script = f"""
import sys, numpy as np
sys.path.insert(0, {str(exported)!r})
from egcbf_runtime import Controller
i = dict(np.load({str(tmp_path / "in.npz")!r}))
u, info = Controller.load({str(exported)!r}).step(i["x"], i["goal"], i["others"], None, i["hits"], None, i["acc"],
                                                  (i["centers"], i["radii"]))
bad = [m for m in sys.modules if m == "torch" or m.startswith(("torch.", "egcbf.", "groupcanon"))]
assert not bad and "egcbf" not in sys.modules, bad
np.savez({str(tmp_path / "out.npz")!r}, u=u, command=info["command"])
"""
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120)
    got = np.load(tmp_path / "out.npz")
    u, info = (
        load_runtime(exported)
        .Controller.load(exported)
        .step(
            x.numpy(), goal.numpy(), others.numpy(), None, hits.numpy(), None, a.numpy(), tuple(o.numpy() for o in obs)
        )
    )
    assert np.array_equal(got["u"], u) and np.array_equal(got["command"], info["command"])


def test_bad_directories_and_inputs_are_named(exported, tmp_path):
    mod = load_runtime(exported)
    with pytest.raises(mod.ExportError, match="not a directory"):
        mod.Controller.load(tmp_path / "missing")
    with pytest.raises(mod.ExportError, match="is not an exported controller"):
        mod.Controller.load(tmp_path)
    (tmp_path / "controller.json").write_text(json.dumps({"format": "something else"}))
    (tmp_path / "policy.onnx").write_bytes(b"")
    with pytest.raises(mod.ExportError, match="format 'something else'"):
        mod.Controller.load(tmp_path)
    rt = mod.Controller.load(exported)
    x = np.zeros(18)
    x[3:12] = np.eye(3).reshape(9)
    goal, none = np.ones(3), np.zeros((0, 18))
    with pytest.raises(ValueError, match=r"state must have shape \(18,\)"):
        rt.step(x[:17], goal, none)
    with pytest.raises(ValueError, match=r"neighbours must have shape \(K, 18\)"):
        rt.step(x, goal, np.zeros((2, 17)))
    with pytest.raises(ValueError, match="goal holds NaN or inf"):
        rt.step(x, np.full(3, np.nan), none)
    with pytest.raises(ValueError, match="is not a rotation"):
        rt.step(np.zeros(18), goal, none)
    with pytest.raises(ValueError, match=r"neighbour_mask must be a bool array of shape \(1,\)"):
        rt.step(x, goal, np.zeros((1, 18)), np.ones(1))
    with pytest.raises(ValueError, match=r"accelerations must have shape \(2, 3\)"):
        rt.step(x, goal, np.zeros((1, 18)), accelerations=np.zeros((1, 3)))
    with pytest.raises(ValueError, match="agent's own"):
        rt.step(x, goal, none, accelerations=np.full((1, 3), np.nan))
    with pytest.raises(ValueError, match="obstacles must be a pair"):
        rt.step(x, goal, none, obstacles=np.zeros((1, 3)))
    # a corrupt message (NaN) is dropped and counted; a masked row is not read at all
    near = x.copy()
    near[:3] = (0.3, 0.0, 0.0)
    u_one, _ = rt.step(x, goal, near[None])
    rows = np.stack((np.full(18, np.nan), near, np.full(18, np.nan)))
    u, info = rt.step(x, goal, rows, np.array([True, True, False]))
    assert np.array_equal(u, u_one) and info["rejected_neighbours"] == 1 and info["num_neighbours"] == 1


def test_the_command_refuses_what_it_cannot_export(exported, tmp_path):
    base = ["export", "--checkpoint", str(ROOT / "egcbf+"), "--out", str(tmp_path / "d")]
    for extra, msg in (
        (["--controller", "egcbf+:cbf"], "not 'cbf'"),
        (["--controller", "gcbf+:dcbf"], "holds a egcbf+ policy, not gcbf+"),
        (["--controller", "egcbf+:dcbf", "--format", "onnx"], "pass one of --format"),
        ([], "pass one of --format"),
    ):
        res = CliRunner().invoke(app, [*base, *extra])
        assert res.exit_code == 2 and msg in res.output, res.output
    args = ["export", "--controller", "policy:dcbf", "--checkpoint", str(ROOT / "egcbf+"), "--out", str(exported)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2 and "--overwrite" in res.output
