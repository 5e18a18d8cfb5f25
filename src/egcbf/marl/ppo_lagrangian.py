"""IPPO with a Lagrangian cost constraint, trained through :class:`egcbf.env.torchrl.SwarmTorchRLEnv`.

Built from TorchRL's components (the optional ``marl`` extra): a ``ProbabilisticActor`` over
:class:`~egcbf.marl.networks.MarlActor` (independent normal commands), a ``ValueOperator`` over
:class:`~egcbf.marl.networks.MarlCritic`, a ``Collector``, ``ClipPPOLoss`` with its GAE value estimator. The
actor's distribution is over normalized commands of the robot's command interface (the quadrotor's world
acceleration, :mod:`egcbf.marl.networks`); the collector's policy turns each sampled command into the environment's
body control (clipped to the bounds), and the loss scores the commands. All agents share the actor and the critic
and each reads only its own observation (IPPO).

The constraint: keep the expected collision cost per agent-step below ``cost_budget``. Each iteration optimizes the
Lagrangian's reward ``r - lagrange * c`` and then moves the multiplier by dual ascent,
``lagrange <- clip(lagrange + lagrange_lr * (mean cost - cost_budget), 0, lagrange_max)`` (the PPO-Lagrangian of
Ray et al., 2019, in its penalized-reward form with one critic).

    python -m egcbf.marl.ppo_lagrangian --out runs/ippo-lag --max-minutes 60

writes ``OUT/model.safetensors`` + ``OUT/marl.json`` after every iteration (the newest; training stops cleanly on
Ctrl-C with it kept) and ``OUT/metrics.csv`` (one row per iteration).
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import torch

from .checkpoint import MarlTrainConfig, make_command_interface, save_marl
from .networks import MarlActor, MarlCritic

try:
    from tensordict.nn import TensorDictModule, TensorDictSequential
    from torchrl.collectors import Collector
    from torchrl.modules import IndependentNormal, ProbabilisticActor, ValueOperator
    from torchrl.objectives import ClipPPOLoss, ValueEstimators

    from ..env.torchrl import SwarmTorchRLEnv
except ImportError as err:  # pragma: no cover - exercised by the suite without the extra
    raise ImportError(
        "egcbf.marl.ppo_lagrangian needs TorchRL and TensorDict, the optional `marl` extra: pip install -e '.[marl]'"
    ) from err

__all__ = ["METRICS", "train"]

OBS = tuple(("agents", "observation", k) for k in MarlActor.observation_keys)
#: the columns of metrics.csv
METRICS = ("iteration", "frames", "wall_s", "reward", "cost", "lagrange", "loss_objective", "loss_critic", "entropy")


COMMAND = ("agents", "command")


def build_modules(
    config: MarlTrainConfig, env: SwarmTorchRLEnv
) -> tuple[MarlActor, MarlCritic, object, object, object]:
    """The actor and critic networks and their TorchRL wrappers: the ``ProbabilisticActor`` over normalized
    commands (``("agents", "command")``, what the PPO loss scores), the collector's policy (that actor, then the
    command turned into the environment's ``("agents", "action")`` by :meth:`MarlActor.to_control`) and the
    ``ValueOperator``."""
    robot, radius = env.task.robot, env.config.comm_radius
    interface = make_command_interface(config, robot)
    actor_net = MarlActor(robot, radius, interface, config.net)
    critic_net = MarlCritic(robot, radius, config.net)
    module = TensorDictModule(actor_net, in_keys=list(OBS), out_keys=[("agents", "loc"), ("agents", "scale")])
    actor = ProbabilisticActor(module, in_keys={"loc": ("agents", "loc"), "scale": ("agents", "scale")},
                               out_keys=[COMMAND], distribution_class=IndependentNormal,
                               return_log_prob=True, log_prob_key=("agents", "sample_log_prob"))  # fmt: skip
    to_action = TensorDictModule(actor_net.to_control, in_keys=[("agents", "observation", "state"), COMMAND],
                                 out_keys=[("agents", "action")])  # fmt: skip
    policy = TensorDictSequential(actor, to_action)
    value = ValueOperator(critic_net, in_keys=list(OBS), out_keys=[("agents", "state_value")])
    return actor_net, critic_net, actor, policy, value


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"{out} is not empty; pass --overwrite to replace its checkpoint")


def train(config: MarlTrainConfig, out: str | Path, *, overwrite: bool = False, log=print) -> Path:
    """Train (module doc) into ``out``; returns it. Deterministic given ``config.seed`` on one thread."""
    out = Path(out)
    _check_out(out, overwrite)
    # advantages are normalized over every agent-sample together (the agents share one policy): intended
    warnings.filterwarnings("ignore", message="You requested advantage normalization", category=UserWarning)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(config.seed)
    env = SwarmTorchRLEnv(config.env_config(), config.task, seed=config.seed)
    actor_net, critic_net, actor, policy, value = build_modules(config, env)
    frames = config.num_envs * config.rollout_steps
    collector = Collector(env, policy, frames_per_batch=frames, total_frames=frames * config.iterations,
                          auto_register_policy_transforms=False)  # fmt: skip
    loss = ClipPPOLoss(actor, value, clip_epsilon=config.clip_epsilon, entropy_coeff=config.entropy_coef,
                       normalize_advantage=True, normalize_advantage_exclude_dims=())  # fmt: skip
    loss.set_keys(reward=("agents", "reward"), action=COMMAND, value=("agents", "state_value"),
                  sample_log_prob=("agents", "sample_log_prob"), advantage=("agents", "advantage"),
                  value_target=("agents", "value_target"), done=("agents", "done"),
                  terminated=("agents", "terminated"))  # fmt: skip
    loss.make_value_estimator(ValueEstimators.GAE, gamma=config.gamma, lmbda=config.lmbda)
    optim = torch.optim.Adam(loss.parameters(), lr=config.lr)
    lagrange = float(config.lagrange_init)
    start = time.monotonic()
    metrics = out / "metrics.csv"
    with metrics.open("w", newline="") as fh:
        csv.writer(fh).writerow(METRICS)
    total = 0
    try:
        for it, data in enumerate(collector):
            n = env.config.num_agents
            shape = data["next", "agents", "reward"].shape  # (B, T, N, 1)
            for key in ("done", "terminated"):
                data.set(("next", "agents", key), data["next", key].unsqueeze(-2).expand(shape))
            reward = data["next", "agents", "reward"].clone()
            cost = data["next", "agents", "info", "cost"]
            data.set(("next", "agents", "reward"), reward - lagrange * cost)
            with torch.no_grad():
                loss.value_estimator(
                    data, params=loss.critic_network_params, target_params=loss.target_critic_network_params
                )
            flat = data.reshape(-1)
            per_agent = flat.numel() * n
            steps = max(1, per_agent // config.minibatch_agents)
            logs = []
            for _ in range(config.epochs):
                for idx in torch.randperm(flat.numel()).chunk(steps):
                    values = loss(flat[idx])
                    objective = values["loss_objective"] + values["loss_critic"] + values["loss_entropy"]
                    optim.zero_grad()
                    objective.backward()
                    torch.nn.utils.clip_grad_norm_(loss.parameters(), config.max_grad_norm)
                    optim.step()
                    logs.append([float(values[k].detach()) for k in ("loss_objective", "loss_critic", "entropy")])
            collector.update_policy_weights_()
            mean_cost = float(cost.mean())
            lagrange = min(max(lagrange + config.lagrange_lr * (mean_cost - config.cost_budget), 0.0),
                           config.lagrange_max)  # fmt: skip
            total += per_agent
            wall = time.monotonic() - start
            means = torch.tensor(logs).mean(0).tolist()
            row = [it, total, round(wall, 2), float(reward.mean()), mean_cost, lagrange, *means]
            with metrics.open("a", newline="") as fh:
                csv.writer(fh).writerow(row)
            save_marl(out, config, actor_net, critic_net, lagrange, iteration=it, frames=total, wall_s=round(wall, 2))
            if it % 10 == 0:
                log(f"iteration {it}: {total} agent-steps, {wall / 60:.1f} min, reward {row[3]:.3f}, "
                    f"cost {mean_cost:.4f}, lagrange {lagrange:.2f}")  # fmt: skip
            if wall > 60 * config.max_minutes or it + 1 >= config.iterations:
                break
    except KeyboardInterrupt:
        log("interrupted: the newest checkpoint is kept")
    finally:
        collector.shutdown()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--robot", default="quadrotor")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-minutes", type=float, default=60.0)
    ap.add_argument("--iterations", type=int, default=100_000)
    ap.add_argument("--num-envs", type=int, default=None)
    ap.add_argument("--num-agents", type=int, default=None)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    changes = {"robot": args.robot, "seed": args.seed, "max_minutes": args.max_minutes, "iterations": args.iterations}
    if args.num_envs:
        changes["num_envs"] = args.num_envs
    if args.num_agents:
        changes["num_agents"] = args.num_agents
    config = replace(MarlTrainConfig(), **changes)
    try:
        train(config, args.out, overwrite=args.overwrite)
    except FileExistsError as err:
        print(f"Error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
