"""Trace every obstacle collision of the nominal controller behind the LiDAR-only ``dcbf`` filter (validation seed
777 by default; docs/safety_filters.md, "LiDAR-only sensing"): for each agent that touches an obstacle, the sphere's
radius, how many steps it had been seen by the agent's LiDAR, the agent's speed and closing speed at contact, the
steps whose filter QP needed slack among the 12 before, and the largest gap between its nearest hit distance and
its true surface distance over those steps.

    .venv/bin/python docs/diagnose_lidar_collisions.py --lidar-hits point --episodes 2
"""

import argparse
import dataclasses

import torch

from egcbf.control.filters import FilterConfig, FilteredController
from egcbf.env import EnvConfig
from egcbf.env.swarm import SwarmEnv, cast_lidar
from egcbf.evaluate.episodes import concat_states, episode_seed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lidar-hits", default="point", choices=("point", "plane"))
    ap.add_argument("--episodes", type=int, default=2)
    ap.add_argument("--seed", type=int, default=777)
    ap.add_argument("--num-agents", type=int, default=512)
    args = ap.parse_args()
    torch.set_num_threads(1)
    n = args.num_agents
    cfg = EnvConfig.for_robot("quadrotor", num_agents=n, area_size=4.0, num_obstacles=8)
    ctrl = FilteredController(None, None, FilterConfig.for_kind("dcbf", obstacle_sensing="lidar",
                                                                lidar_hits=args.lidar_hits))  # fmt: skip
    env1 = SwarmEnv(dataclasses.replace(cfg, num_envs=1))
    state = concat_states([env1.reset(episode_seed(args.seed, n, e)) for e in range(args.episodes)])
    env = SwarmEnv(dataclasses.replace(cfg, num_envs=args.episodes))
    obs = state.obstacles
    b, k = args.episodes, obs.num_obstacles
    first_seen = torch.full((b, n, k), -1)
    collided = torch.zeros(b, n, dtype=torch.bool)
    trace = []  # per step: (true surface distance, nearest hit distance, QP slack or brake)
    events = []
    for t in range(cfg.max_steps):
        scan = cast_lidar(env.config, state.positions, state.robot.heading(state.x), obs)
        gap = (scan.points[..., None, :] - obs.centers[:, None, None]).norm(dim=-1) - obs.radii[:, None, None]
        owner = gap.abs().argmin(-1)  # the sphere each hit lies on
        seen = torch.stack([((owner == j) & scan.valid).any(-1) for j in range(k)], -1)
        first_seen[seen & (first_seen < 0)] = t
        surface = ((state.positions[:, :, None] - obs.centers[:, None]).norm(dim=-1) - obs.radii[:, None]).min(-1)[0]
        u, info = ctrl(state, env.config)
        bad = torch.as_tensor(info["slack_mask"] | info["failed_mask"]).reshape(b, n)
        trace.append((surface, scan.distance.min(-1)[0], bad))
        p, v = state.positions, state.x[..., 12:15]
        state, step = env.step(state, u)
        for e, i in (step.obstacle_collision & ~collided).nonzero().tolist():
            j = int(((state.positions[e, i] - obs.centers[e]).norm(dim=-1) - obs.radii[e]).argmin())
            normal = (obs.centers[e, j] - p[e, i]) / (obs.centers[e, j] - p[e, i]).norm()
            last = trace[-12:]
            events.append({
                "step": t, "radius": round(float(obs.radii[e, j]), 3), "seen_for": t - int(first_seen[e, i, j]),
                "speed": round(float(v[e, i].norm()), 2), "closing": round(float(v[e, i] @ normal), 2),
                "slack_steps_of_12": sum(bool(x[2][e, i]) for x in last),
                "hit_vs_surface_mm": round(1e3 * max(abs(float(x[1][e, i] - x[0][e, i])) for x in last), 1),
            })  # fmt: skip
        collided |= step.collision
    print(f"lidar_hits={args.lidar_hits}, seed {args.seed}, {b} episodes, N = {n}: {len(events)} obstacle "
          f"collision(s), {int(collided.sum())} agents in any collision")  # fmt: skip
    for ev in events:
        print(ev)


if __name__ == "__main__":
    main()
