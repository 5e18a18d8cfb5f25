"""Our swarms through the multi-agent RL ecosystem's interfaces: PettingZoo's ParallelEnv and TorchRL's EnvBase.

Needs the optional `marl` extra (`pip install -e '.[marl]'`; `make setup` installs it). Run from the repository root:

    .venv/bin/python examples/marl_envs.py

1. a PettingZoo episode of 8 quadrotors among 4 obstacles, each agent commanded from its own observation alone
   (the nominal controller, a stand-in for your policy), with rewards and costs summed per agent;
2. a batched TorchRL rollout of 4 scenes x 16 agents with a small random Gaussian policy written as a
   TensorDictModule (plug in your TorchRL or BenchMARL algorithm instead), and the cost rate it pays;
3. checks that both interfaces step the same simulation as egcbf's own SwarmEnv (float64, 1e-12).

Prints OK when every check holds.
"""

from __future__ import annotations

import sys

import numpy as np
import torch

try:
    from tensordict.nn import TensorDictModule

    from egcbf.env.pettingzoo import parallel_env
    from egcbf.env.torchrl import SwarmTorchRLEnv
except ImportError as err:
    sys.exit(f"{err}")

from egcbf.env import EnvConfig, SwarmEnv
from egcbf.robots import make_robot

F64 = torch.float64


def pettingzoo_episode() -> np.ndarray:
    """One episode through PettingZoo; returns the agents' states over time ``(T, N, S)``."""
    env = parallel_env(robot="quadrotor", num_agents=8, num_obstacles=4, max_steps=64, dtype=F64)
    robot = make_robot("quadrotor")
    observations, _ = env.reset(seed=0)
    space = env.observation_space("agent_0")
    print(f"PettingZoo: {len(env.possible_agents)} agents; observation {dict(space.spaces)}")
    print(f"  action space {env.action_space('agent_0')}; global state {env.state_space.shape}")
    totals = dict.fromkeys(env.possible_agents, 0.0)
    costs = dict.fromkeys(env.possible_agents, 0.0)
    states = []
    while env.agents:
        actions = {}
        for agent in env.agents:  # a decentralized policy: each agent reads only its own observation
            obs = observations[agent]
            x, goal = torch.as_tensor(obs["state"]), torch.as_tensor(obs["goal"])
            actions[agent] = robot.nominal_control(x, goal).numpy()
        observations, rewards, _, _, infos = env.step(actions)
        states.append(np.stack([observations[a]["state"] for a in env.possible_agents]))
        for agent in rewards:
            totals[agent] += rewards[agent]
            costs[agent] += infos[agent]["cost"]
    print(f"  return per agent {np.mean(list(totals.values())):.2f}, collisions (cost) per agent "
          f"{np.mean(list(costs.values())):.3f}")  # fmt: skip
    return np.stack(states)


class GaussianPolicy(torch.nn.Module):
    """A per-agent policy over the observation: the nominal command plus Gaussian noise (a stand-in for a learned
    network; shapes (B, N, ...) in, (B, N, k) out)."""

    def __init__(self, robot, scale: float = 0.1):
        super().__init__()
        self.robot, self.scale = robot, scale
        lo, hi = robot.control_bounds(torch.zeros((), dtype=torch.float32))
        self.register_buffer("half_width", (hi - lo) / 2)

    def forward(self, state, goal, neighbours, neighbour_mask):
        u = self.robot.nominal_control(state, goal)
        return self.robot.clip_control(u + self.scale * self.half_width * torch.randn_like(u))


def torchrl_rollout() -> None:
    env = SwarmTorchRLEnv(EnvConfig.for_robot("quadrotor", num_agents=16, num_envs=4, max_steps=64), seed=0)
    keys = [("agents", "observation", k) for k in ("state", "goal", "neighbours", "neighbour_mask")]
    policy = TensorDictModule(GaussianPolicy(env.task.robot), in_keys=keys, out_keys=[("agents", "action")])
    torch.manual_seed(0)
    td = env.rollout(64, policy)
    reward = td["next", "agents", "reward"]
    cost = td["next", "agents", "info", "cost"]
    print(f"TorchRL: batch {tuple(td.batch_size)} (scenes, steps); reward {tuple(reward.shape)}; mean reward "
          f"{float(reward.mean()):.3f}; cost rate {float(cost.mean()):.4f} per agent-step")  # fmt: skip


def direct_states() -> np.ndarray:
    cfg = EnvConfig.for_robot("quadrotor", num_agents=8, num_obstacles=4, max_steps=64)
    env = SwarmEnv(cfg, dtype=F64)
    state, out = env.reset(0), []
    for _ in range(64):
        state, _ = env.step(state, env.robot.nominal_control(state.x, state.goals))
        out.append(state.x[0].numpy())
    return np.stack(out)


def main() -> int:
    through_pettingzoo = pettingzoo_episode()
    torchrl_rollout()
    gap = float(np.abs(through_pettingzoo - direct_states()).max())
    print(f"PettingZoo episode against SwarmEnv: largest state difference {gap:.1e}")
    if gap > 1e-12:
        print("FAILED: the PettingZoo episode left the simulation")
        return 1
    print("OK")
    return 0


if __name__ == "__main__":
    sys.exit(main())
