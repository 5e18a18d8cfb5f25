"""Fly the shipped EGCBF+ policy the way robots would, one controller per agent, in wind and with one control
period of actuation latency, without and with the agents' on-board handling (:class:`egcbf.faults.onboard.Onboard`: a
Smith predictor over the latency and a disturbance observer; docs/deploy.md, "Latency and wind on board").

Each agent runs its own :class:`egcbf.deploy.agent.AgentController` on what it knows: its own state, its goal, and its
neighbours' broadcasts (with the handling, each broadcasts the state its next command will act on). The world is
the simulator's: its dynamics, 1 m/s^2 of wind with gusts, and the latency (:class:`egcbf.faults.FaultProcess`
with the physical faults only).

    python examples/onboard_robot.py      # prints each run's reach and safety; OK if the handling brings them home
"""

from __future__ import annotations

import torch

from egcbf.deploy.agent import AgentController
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.faults import FaultConfig, FaultProcess
from egcbf.faults.onboard import Onboard

torch.set_num_threads(1)
WORLD = FaultConfig(wind=(1.0, 0.0, 0.0), gust=0.5, act_delay=1)  # what the robots do not control
AGENTS, STEPS, SEED = 6, 320, 11  # 8 s at 25 ms


def fly(ctrl: AgentController, handled: bool) -> tuple[float, float]:
    """The fraction of agents at their goals at the end and the fraction never in a collision."""
    config = EnvConfig(num_agents=AGENTS, num_envs=1, area_size=2.5, num_obstacles=0, max_steps=STEPS)
    env = SwarmEnv(config)
    state = env.reset(SEED)
    world = FaultProcess(WORLD, config, ctrl.robot, [SEED])
    onboard = [Onboard(ctrl.robot, ctrl.env_config, act_delay=WORLD.act_delay, predict=True,
                       observe_disturbance=True) for _ in range(AGENTS)]  # fmt: skip
    safe = torch.ones(AGENTS, dtype=torch.bool)
    no_hits = torch.zeros(0, 3)
    for _ in range(STEPS):
        seen = world.observe(state)  # exact estimates: the faults here are the latency and the wind
        x, goals = seen.x[0], seen.goals[0]
        # each agent's state to command for, which it also broadcasts
        x_for = torch.stack([agent.estimate(x[i], goals[i]) for i, agent in enumerate(onboard)]) if handled else x
        u = []
        for i in range(AGENTS):
            neighbours = torch.cat((x_for[:i], x_for[i + 1 :]))
            ui, _ = ctrl(x_for[i], goals[i], neighbours, no_hits)
            u.append(onboard[i].command(ui) if handled else ui)
        state, info = env.step(state, world.actuate(torch.stack(u)[None], state))
        state = world.push(state)
        safe &= ~info.collision[0]
    reached = torch.linalg.vector_norm(state.x[0, :, :3] - state.goals[0], dim=-1) < 2 * config.agent_radius
    return float(reached.float().mean()), float(safe.float().mean())


def main() -> None:
    ctrl = AgentController.from_checkpoint("checkpoints/egcbf+")
    runs = {handled: fly(ctrl, handled) for handled in (False, True)}
    for handled, (reach, safe) in runs.items():
        name = "with Onboard (predictor + observer)" if handled else "controller alone"
        print(f"{name:38s} at the goal {100 * reach:5.1f} %   never collided {100 * safe:5.1f} %")
    (reach_off, _), (reach_on, safe_on) = runs[False], runs[True]
    assert reach_on == 1.0 and safe_on == 1.0, "the handled swarm should arrive, safely"
    assert reach_on > reach_off, "the latency and the wind should keep the unhandled swarm off its goals"
    print("OK")


if __name__ == "__main__":
    main()
