"""The PettingZoo and TorchRL adapters (the `marl` extra): their libraries' own API tests for every registered
robot, with and without obstacles, and rollouts through each equal to stepping SwarmEnv directly."""

import subprocess
import sys

import numpy as np
import pytest
import torch

from egcbf.env import EnvConfig, SwarmEnv
from egcbf.robots import ROBOTS

F64 = torch.float64
OBSTACLES = (0, 3)


def _pettingzoo():
    pytest.importorskip("pettingzoo")
    pytest.importorskip("gymnasium")
    from egcbf.env.pettingzoo import parallel_env

    return parallel_env


def _torchrl():
    pytest.importorskip("torchrl")
    from egcbf.env.torchrl import SwarmTorchRLEnv

    return SwarmTorchRLEnv


@pytest.mark.parametrize("obstacles", OBSTACLES)
@pytest.mark.parametrize("robot", sorted(ROBOTS))
def test_pettingzoo_api_and_seed_tests_pass(robot, obstacles):
    parallel_env = _pettingzoo()
    from pettingzoo.test import parallel_api_test, parallel_seed_test

    make = lambda: parallel_env(robot=robot, num_agents=4, num_obstacles=obstacles, max_steps=12)  # noqa: E731
    env = make()
    parallel_api_test(env, num_cycles=30)
    parallel_seed_test(make, num_cycles=30)
    env.reset(seed=3)
    assert env.state_space.contains(env.state())


@pytest.mark.parametrize("obstacles", OBSTACLES)
@pytest.mark.parametrize("robot", sorted(ROBOTS))
def test_torchrl_specs_pass(robot, obstacles):
    env_cls = _torchrl()
    from torchrl.envs.utils import check_env_specs

    env = env_cls(EnvConfig.for_robot(robot, num_agents=4, num_envs=3, num_obstacles=obstacles, max_steps=6))
    check_env_specs(env, seed=0)
    td = env.rollout(8, break_when_any_done=False)  # through an automatic reset of all three scenes
    assert td.batch_size == (3, 8)
    assert td["next", "done"][:, 5].all() and not td["next", "done"][:, :5].any()


def _direct(robot, obstacles, seed, steps):
    cfg = EnvConfig.for_robot(robot, num_agents=6, num_obstacles=obstacles, max_steps=steps)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(seed)
    xs = []
    for _ in range(steps):
        state, _ = env.step(state, env.robot.nominal_control(state.x, state.goals))
        xs.append(state.x)
    return torch.stack(xs), env.robot


@pytest.mark.parametrize("robot", sorted(ROBOTS))
def test_nominal_rollout_through_pettingzoo_equals_swarm_env(robot):
    parallel_env = _pettingzoo()
    expected, r = _direct(robot, 3, 5, 10)
    env = parallel_env(robot=robot, num_agents=6, num_obstacles=3, max_steps=10, dtype=F64)
    obs, _ = env.reset(seed=5)
    got = []
    while env.agents:
        actions = {}
        for agent in env.agents:
            x, goal = (torch.as_tensor(obs[agent][k]) for k in ("state", "goal"))
            actions[agent] = r.nominal_control(x, goal).numpy()  # from the agent's own observation alone
        obs, _, _, truncations, infos = env.step(actions)
        got.append(np.stack([obs[a]["state"] for a in env.possible_agents]))
        assert set(infos["agent_0"]) >= {"cost", "collision", "reached"}
    assert len(got) == 10 and all(truncations.values())
    torch.testing.assert_close(torch.as_tensor(np.stack(got)), expected[:, 0], rtol=0, atol=1e-12)


@pytest.mark.parametrize("robot", sorted(ROBOTS))
def test_nominal_rollout_through_torchrl_equals_swarm_env(robot):
    env_cls = _torchrl()
    from tensordict.nn import TensorDictModule

    expected, r = _direct(robot, 3, 5, 10)
    env = env_cls(EnvConfig.for_robot(robot, num_agents=6, num_obstacles=3, max_steps=10), dtype=F64, seed=5)

    class Nominal(torch.nn.Module):
        def forward(self, x, goal):
            return r.nominal_control(x, goal)

    keys = [("agents", "observation", "state"), ("agents", "observation", "goal")]
    policy = TensorDictModule(Nominal(), in_keys=keys, out_keys=[("agents", "action")])
    td = env.rollout(10, policy)
    got = td["next", "agents", "observation", "state"]  # (B = 1, T, N, S)
    torch.testing.assert_close(got[0], expected[:, 0], rtol=0, atol=1e-12)
    assert td["next", "truncated"][0, -1].all()


def test_pettingzoo_refuses_missing_actions_and_steps_after_the_end():
    parallel_env = _pettingzoo()
    env = parallel_env(num_agents=3, max_steps=1)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="missing: agent_2"):
        env.step({a: env.action_space(a).sample() for a in env.agents[:2]})
    env.step({a: env.action_space(a).sample() for a in env.agents})
    with pytest.raises(RuntimeError, match="call reset"):
        env.step({})
    with pytest.raises(KeyError, match="agent_7"):
        env.observation_space("agent_7")


def test_torchrl_refuses_a_partial_reset():
    env_cls = _torchrl()
    from tensordict import TensorDict

    env = env_cls(EnvConfig(num_agents=3, num_envs=2))
    env.reset()
    with pytest.raises(ValueError, match="partial"):
        env.reset(TensorDict({"_reset": torch.tensor([[True], [False]])}, batch_size=[2]))


def test_torchrl_episodes_are_seeded_and_differ():
    env_cls = _torchrl()
    a, b = env_cls(EnvConfig(num_agents=3, num_envs=2)), env_cls(EnvConfig(num_agents=3, num_envs=2))
    a.set_seed(11)
    b.set_seed(11)
    first_a, first_b = a.reset(), b.reset()
    key = ("agents", "observation", "state")
    assert torch.equal(first_a[key], first_b[key])
    assert not torch.equal(a.reset()[key], first_a[key])


def test_without_the_extra_the_adapters_name_it_and_the_core_never_imports_them():
    code = (
        "import sys\n"
        "for m in ('pettingzoo', 'gymnasium', 'torchrl', 'tensordict'): sys.modules[m] = None\n"
        "import egcbf, egcbf.env, egcbf.env.task, egcbf.cli, egcbf.control\n"
        "for mod in ('egcbf.env.pettingzoo', 'egcbf.env.torchrl'):\n"
        "    try:\n"
        "        __import__(mod)\n"
        "    except ImportError as err:\n"
        "        assert \"pip install -e '.[marl]'\" in str(err), err\n"
        "    else:\n"
        "        raise AssertionError(mod + ' imported without its extra')\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
