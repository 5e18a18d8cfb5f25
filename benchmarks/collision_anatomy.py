"""Where does a policy collide? Every new agent-agent contact of a checkpoint's policy alone, with its context.

Runs the policy (no filter) on validation episodes (seed 777 by default, disjoint from training, selection and the
evaluation seeds of ``egcbf eval`` / ``egcbf reproduce``) and records, for each pair that comes closer than two agent
radii at a step where it was not before: the step, the pair's closing speed (m/s) and both agents' speeds and
distances to their goals just before. Prints quartiles; ``--out FILE.json`` writes them with the command.

    python benchmarks/collision_anatomy.py --checkpoint checkpoints/egcbf+ --num-agents 512 --area 4 --episodes 1
"""

from __future__ import annotations

import argparse
import statistics

import torch
from validation_scene import add_scene_arguments, write_record

from egcbf.env import EnvConfig, SwarmEnv
from egcbf.evaluate.episodes import episode_seed
from egcbf.train.checkpoint import load_controller


def contacts(checkpoint: str, num_agents: int, area: float, episodes: int, seed: int) -> list[dict]:
    """New contacts of all episodes: dicts of ``step``, ``closing`` (m/s), ``speed_fast`` / ``speed_slow`` (m/s),
    ``goal_near`` / ``goal_far`` (m, the pair's nearer and farther goal distance)."""
    ctrl, cfg = load_controller(checkpoint)
    env_cfg = EnvConfig.for_robot(
        cfg.robot, num_agents=num_agents, area_size=area, num_obstacles=0, num_envs=1, **(cfg.env_overrides or {})
    )
    env = SwarmEnv(env_cfg)
    contact = 2 * env_cfg.agent_radius
    out = []
    for e in range(episodes):
        s = env.reset(episode_seed(seed, num_agents, e))
        for t in range(env_cfg.max_steps):
            u, _ = ctrl(s, env_cfg)
            p, v = s.x[0, :, 0:3], s.x[0, :, 12:15]
            before = torch.cdist(p, p).fill_diagonal_(float("inf")) < contact
            s, _ = env.step(s, u)
            p2 = s.x[0, :, 0:3]
            new = (torch.cdist(p2, p2).fill_diagonal_(float("inf")) < contact) & ~before
            for i, j in new.nonzero().tolist():
                if i > j:
                    continue
                dp, dv = p[j] - p[i], v[j] - v[i]
                goals = sorted(float((s.goals[0, k] - p[k]).norm()) for k in (i, j))
                speeds = sorted(float(v[k].norm()) for k in (i, j))
                out.append({"step": t, "closing": float(-(dp @ dv) / dp.norm()), "speed_slow": speeds[0],
                            "speed_fast": speeds[1], "goal_near": goals[0], "goal_far": goals[1]})  # fmt: skip
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(ap, num_agents=512, area=4.0, episodes=1)
    args = ap.parse_args()
    torch.set_num_threads(1)
    found = contacts(args.checkpoint, args.num_agents, args.area, args.episodes, args.seed)
    print(f"{args.checkpoint}: {len(found)} new contacts in {args.episodes} episode(s), N = {args.num_agents}, "
          f"l = {args.area}, seed {args.seed}")  # fmt: skip
    quartiles = {}
    for key in ("step", "closing", "speed_fast", "speed_slow", "goal_near", "goal_far"):
        values = [c[key] for c in found]
        if len(values) >= 2:
            q = statistics.quantiles(values, n=4)
            quartiles[key] = [min(values), *q, max(values)]
            qs = " ".join(f"{x:6.2f}" for x in q)
            print(f"  {key:10s} min {min(values):6.2f}  quartiles {qs}  max {max(values):6.2f}")
    write_record(args, contacts=len(found), min_q1_q2_q3_max=quartiles)


if __name__ == "__main__":
    main()
