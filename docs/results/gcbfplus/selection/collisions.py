"""The first agent-agent collision of every agent, with its context (issue 26, session 41; validation seeds only).

    .venv/bin/python docs/results/gcbfplus/selection/collisions.py CHECKPOINT N L EPISODES SEED [STEPS]

Prints the safe rate, then one line per colliding agent: episode, step, the agent and the closest other one, their
distance (in agent radii), speeds (m/s) and distances to their own goals (in radii; <= 0.5: parked at the goal).
``STALE=1`` keeps a frozen car's speed in its state, the reference's freeze (docs/robots.md), instead of parking it.
"""

import dataclasses
import os
import sys

import torch

from egcbf.train.checkpoint import load_controller
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.evaluate.episodes import concat_states, episode_seed

torch.set_num_threads(1)
if os.environ.get("STALE") == "1":
    from egcbf.robots.planar import HeadingSpeedRobot

    HeadingSpeedRobot.parked = lambda self, x: x

ckpt, n, side, episodes, seed = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
steps = int(sys.argv[6]) if len(sys.argv) > 6 else 256
controller, cfg = load_controller(ckpt)
config = EnvConfig.for_robot(cfg.model.robot, num_agents=n, area_size=side, num_obstacles=0, max_steps=steps)
seeds = [episode_seed(seed, n, e) for e in range(episodes)]  # the episodes of `egcbf eval --seed SEED`
state = concat_states([SwarmEnv(dataclasses.replace(config, num_envs=1)).reset(s) for s in seeds])
env = SwarmEnv(dataclasses.replace(config, num_envs=len(seeds)))
r = config.agent_radius
hit = torch.zeros(len(seeds), n, dtype=torch.bool)
events = []
for t in range(steps):
    u, _ = controller(state, env.config)
    state, info = env.step(state, u)
    new = info.agent_collision & ~hit
    if new.any():
        p, v = state.x[..., 0:2], state.x[..., 4]
        d = torch.cdist(p, p) + torch.eye(n) * 1e9
        for b, i in new.nonzero().tolist():
            j = int(d[b, i].argmin())
            gap = (state.goals[b, :, :2] - p[b]).norm(dim=-1)
            events.append((b, t, i, j, f"{d[b, i, j] / r:.2f}", f"{v[b, i]:.2f}", f"{v[b, j]:.2f}",
                           f"{gap[i] / r:.1f}", f"{gap[j] / r:.1f}"))  # fmt: skip
    hit |= info.agent_collision
print("agents unsafe", int(hit.sum()), "of", hit.numel(), f"{100 * (1 - hit.float().mean()):.2f}% safe")
print("episode step i j distance/r v_i v_j goal_i/r goal_j/r")
for e in events:
    print(*e)
