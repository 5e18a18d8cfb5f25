"""The MARL baseline (egcbf.marl): its actor's invariances, its checkpoint, a short IPPO-Lagrangian run through
TorchRL (the `marl` extra) and the trained actor as a controller like the others."""

import csv
import json

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.control.resolve import ControllerError, resolve
from egcbf.env import EnvConfig
from egcbf.env.task import SwarmTask, TaskConfig
from egcbf.marl.checkpoint import MarlTrainConfig, load_actor, make_command_interface, read_marl_config, save_marl
from egcbf.marl.networks import MarlActor, MarlCritic, MarlNetConfig

F64 = torch.float64


def _scene(seed, robot="quadrotor", n=10, k=4):
    cfg = EnvConfig.for_robot(robot, num_agents=n, num_envs=2, area_size=1.5, num_obstacles=2)
    task = SwarmTask(cfg, TaskConfig(max_neighbours=k), dtype=F64)
    obs = task.reset(seed)
    return task, obs


def _actor(task, net=None):
    interface = make_command_interface(MarlTrainConfig(robot=task.config.robot), task.robot)
    return MarlActor(task.robot, task.config.comm_radius, interface, net).to(F64)


def _trained_like_actor(task, seed):
    """An actor with random (non-zero) weights, so that its residual is not zero."""
    torch.manual_seed(seed)
    actor = _actor(task, MarlNetConfig(hidden=16))
    for p in actor.parameters():
        torch.nn.init.normal_(p, std=0.3)
    return actor


@settings(max_examples=8)
@given(seed=st.integers(0, 2**16))
def test_actor_ignores_row_order_and_masked_rows(seed):
    task, obs = _scene(seed)
    actor = _trained_like_actor(task, seed)
    gen = torch.Generator().manual_seed(seed)
    perm_n = torch.randperm(obs["neighbours"].shape[-2], generator=gen)
    perm_h = torch.randperm(obs["hits"].shape[-2], generator=gen)
    moved = dict(obs)
    moved["neighbours"], moved["neighbour_mask"] = obs["neighbours"][..., perm_n, :], obs["neighbour_mask"][..., perm_n]
    moved["hits"], moved["hit_mask"] = obs["hits"][..., perm_h, :], obs["hit_mask"][..., perm_h]
    noise = torch.randn(moved["neighbours"].shape, generator=gen, dtype=F64)  # garbage in the masked rows
    moved["neighbours"] = torch.where(moved["neighbour_mask"][..., None], moved["neighbours"], noise)
    torch.testing.assert_close(actor.command(moved), actor.command(obs), rtol=0, atol=1e-12)


@settings(max_examples=8)
@given(seed=st.integers(0, 2**16), shift=st.tuples(*[st.floats(-5, 5)] * 3))
def test_actor_is_translation_invariant(seed, shift):
    task, obs = _scene(seed)
    actor = _trained_like_actor(task, seed)
    t = torch.tensor(shift, dtype=F64)
    moved = dict(obs)
    pos = task.robot.position_index if task.robot.position_index is not None else slice(0, 3)
    moved["state"] = obs["state"].clone()
    moved["state"][..., pos] += t
    moved["neighbours"] = obs["neighbours"].clone()
    moved["neighbours"][..., pos] += t
    moved["goal"], moved["hits"] = obs["goal"] + t, obs["hits"] + t
    torch.testing.assert_close(actor.command(moved), actor.command(obs), rtol=0, atol=1e-9)


@pytest.mark.parametrize("robot", ["quadrotor", "double_integrator", "unicycle"])
def test_a_new_actor_is_the_nominal_controller(robot):
    """The quadrotor's actor commands world accelerations (the attitude loop tracks them), the others' their raw
    control: either way a new actor's body control is the nominal controller's wherever the command box does not
    bind (the quadrotor's box caps the nominal law's vertical acceleration at -4.9 m/s^2, as for the learned
    methods)."""
    task, obs = _scene(3, robot)
    actor = _actor(task)
    interface = actor.interface
    assert interface.name == ("accel" if robot == "quadrotor" else "control")
    x, goal = obs["state"], obs["goal"]
    nominal = task.robot.clip_control(task.robot.nominal_control(x, goal))
    if robot == "quadrotor":
        from egcbf.robots.quadrotor.nominal import nominal_acceleration

        free = nominal_acceleration(x, goal, interface.gains) / interface.accel_unit - interface.nominal(x, goal)
        free = free.abs().amax(-1) < 1e-12
        assert 0 < free.sum() < free.numel()  # some agents' commands bind, some do not
    else:
        free = torch.ones(x.shape[:2], dtype=torch.bool)
    torch.testing.assert_close(actor.command(obs)[free], nominal[free], rtol=0, atol=1e-12)
    torch.testing.assert_close(actor.command(obs), actor.to_control(x, interface.nominal(x, goal)), rtol=0, atol=0)
    critic = MarlCritic(task.robot, task.config.comm_radius).to(F64)
    assert critic(*(obs[k] for k in MarlActor.observation_keys)).shape == (2, 10, 1)


def test_checkpoint_round_trip(tmp_path):
    task, obs = _scene(5)
    config = MarlTrainConfig(num_agents=10, net=MarlNetConfig(hidden=16), task=TaskConfig(max_neighbours=4))
    assert MarlTrainConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    actor = _trained_like_actor(task, 5)
    save_marl(tmp_path, config, actor, MarlCritic(task.robot, task.config.comm_radius, config.net), 2.5,
              iteration=7, frames=100, wall_s=1.0)  # fmt: skip
    loaded, cfg = load_actor(tmp_path, dtype=F64)
    assert cfg == config and read_marl_config(tmp_path)[1]["lagrange"] == 2.5
    torch.testing.assert_close(loaded.command(obs), actor.command(obs), rtol=0, atol=0)


TINY = MarlTrainConfig(num_agents=4, num_envs=2, area_size=1.0, num_obstacles=1, episode_steps=12, rollout_steps=8,
                       iterations=3, epochs=1, minibatch_agents=32, lagrange_init=0.5, lagrange_lr=10.0,
                       net=MarlNetConfig(hidden=16), task=TaskConfig(max_neighbours=3))  # fmt: skip


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A three-iteration IPPO-Lagrangian run (the `marl` extra)."""
    pytest.importorskip("torchrl")
    from egcbf.marl.ppo_lagrangian import train

    return train(TINY, tmp_path_factory.mktemp("marl") / "run", log=lambda _: None)


def test_short_ippo_lagrangian_run_and_its_controller(tiny_run):
    from egcbf.marl.ppo_lagrangian import METRICS, train

    out, config = tiny_run, TINY
    rows = list(csv.DictReader((out / "metrics.csv").open()))
    assert tuple(rows[0]) == METRICS and [int(r["iteration"]) for r in rows] == [0, 1, 2]
    lagrange = 0.5  # dual ascent on each iteration's mean cost
    for r in rows:
        lagrange = min(max(lagrange + 10.0 * (float(r["cost"]) - config.cost_budget), 0.0), config.lagrange_max)
        assert float(r["lagrange"]) == pytest.approx(lagrange)
    assert read_marl_config(out)[1]["iteration"] == 2
    with pytest.raises(FileExistsError, match="overwrite"):
        train(config, out, log=lambda _: None)
    built = resolve("policy", out)
    assert built.name == "ippo-lag" and built.robot == "quadrotor" and built.weights_sha256
    assert resolve("ippo-lag", out).name == "ippo-lag"
    task = SwarmTask(config.env_config(), config.task)
    task.reset(0)
    u, _ = built.controller(task.state, task.config)
    assert u.shape == (2, 4, 4) and torch.isfinite(u).all()
    with pytest.raises(ControllerError, match="run-time filters"):
        resolve("ippo-lag:dcbf", out)
    with pytest.raises(ControllerError, match="not egcbf"):
        resolve("egcbf+", out)


def test_the_reproduce_sweep_runs_a_marl_checkpoint(tiny_run, tmp_path):
    """``egcbf reproduce --methods ippo-lag``: the checkpoint is found under CHECKPOINTS/ippo-lag, its cells keyed by
    its weights, and a checkpoint of another seed is refused."""
    import shutil

    import egcbf.reproduce as rp

    shutil.copytree(tiny_run, tmp_path / "ckpt" / "ippo-lag")
    cfg = rp.SweepConfig(methods=("ippo-lag",), obstacle_methods=("ippo-lag",), num_agents=(4,), area=1.0,
                         obstacles=1, episodes=1, max_steps=8, scale_sizes=(), seed_methods=(),
                         checkpoints=tmp_path / "ckpt", out=tmp_path / "cells", baselines=None,
                         workers=1)  # fmt: skip
    records = rp.sweep(cfg, progress=False, log=lambda _: None)
    assert len(records) == 2 and all(r["meta"]["label"] == "IPPO-Lagrangian" for r in records.values())
    digest = rp.store.find_method_checkpoint(cfg.checkpoints, "ippo-lag").sha256
    assert {r["key"]["checkpoint_sha256"] for r in records.values()} == {digest}
    with pytest.raises(ValueError, match="seed"):
        rp.store._find_marl_checkpoint(tmp_path / "ckpt" / "ippo-lag", "ippo-lag", 1)


def test_demo_compares_with_a_marl_checkpoint(tiny_run, tmp_path):
    import shutil
    import subprocess
    import sys

    shutil.copytree(tiny_run, tmp_path / "ckpt" / "ippo-lag")
    args = ["demo", "--checkpoints", str(tmp_path / "ckpt"), "--method", "nominal", "--compare", "ippo-lag",
            "--num-agents", "4", "--area", "1", "--obstacles", "1", "--episodes", "1", "--max-steps", "8", "--out",
            str(tmp_path / "demo"), "--no-render", "--no-progress", "--threads", "1"]  # fmt: skip
    proc = subprocess.run([sys.executable, "-m", "egcbf", *args], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "ippo-lag" in proc.stdout and (tmp_path / "demo" / "summary.md").exists()
