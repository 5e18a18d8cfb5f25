"""Checkpoints of the MARL baselines: ``model.safetensors`` (actor ``actor.*``, critic ``critic.*``, the Lagrange
multiplier ``lagrange``) and ``marl.json`` (the training configuration, the environment it trained on, the
iteration reached), read with the core's safetensors only (no TorchRL)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from ..algo.interface import CommandInterface, make_interface
from ..env.task import TaskConfig
from ..io.atomic import write_text_atomic
from ..robots import Robot
from .networks import MarlActor, MarlCritic, MarlNetConfig

__all__ = [
    "CONFIG_FILE",
    "WEIGHTS_FILE",
    "MarlTrainConfig",
    "is_marl_checkpoint",
    "load_actor",
    "make_command_interface",
    "read_marl_config",
    "save_marl",
]

CONFIG_FILE = "marl.json"
WEIGHTS_FILE = "model.safetensors"


@dataclass(frozen=True)
class MarlTrainConfig:
    """IPPO-Lagrangian's settings (:mod:`egcbf.marl.ppo_lagrangian`).

    Command: the actor acts on the command interface ``interface`` of the robot (:mod:`egcbf.algo.interface`;
    ``None``: the robot's default, the quadrotor's world acceleration, the other robots' raw control).

    Environment: ``num_envs`` scenes of ``num_agents`` agents of ``robot`` in arenas of side ``area_size`` with
    ``num_obstacles`` obstacles (the ``cpu`` recipe's training density: 32 agents, ``l = 2``, 4 obstacles) and
    ``episode_steps`` per episode. Each iteration collects ``rollout_steps`` steps of every scene, estimates
    advantages with GAE (``gamma``, ``lmbda``) on the reward ``r - lagrange * c``, then takes ``epochs`` passes of
    clipped PPO (``clip_epsilon``, ``entropy_coef``) over minibatches of ``minibatch_agents`` agent-samples at
    learning rate ``lr``; the multiplier then moves by ``lagrange_lr * (mean cost - cost_budget)`` (kept in
    ``[0, lagrange_max]``). Training stops after ``iterations`` or ``max_minutes`` of wall time.
    """

    algo: str = "ippo-lag"
    robot: str = "quadrotor"
    interface: str | None = None
    num_agents: int = 32
    area_size: float = 2.0
    num_obstacles: int = 4
    num_envs: int = 8
    episode_steps: int = 256
    rollout_steps: int = 64
    gamma: float = 0.99
    lmbda: float = 0.95
    clip_epsilon: float = 0.2
    entropy_coef: float = 1e-3
    lr: float = 3e-4
    epochs: int = 4
    minibatch_agents: int = 4096
    max_grad_norm: float = 1.0
    cost_budget: float = 1e-3
    lagrange_init: float = 1.0
    lagrange_lr: float = 20.0
    lagrange_max: float = 100.0
    iterations: int = 100_000
    max_minutes: float = 60.0
    seed: int = 0
    net: MarlNetConfig = field(default_factory=MarlNetConfig)
    task: TaskConfig = field(default_factory=TaskConfig)

    def to_dict(self) -> dict:
        return asdict(self)

    @property
    def env_overrides(self) -> dict:
        """The environment settings beyond the robot's defaults the actor was trained with: none (sensing radii and
        LiDAR are the robot's defaults)."""
        return {}

    @classmethod
    def from_dict(cls, d: dict) -> MarlTrainConfig:
        d = dict(d)
        net, task = MarlNetConfig(**d.pop("net", {})), TaskConfig(**d.pop("task", {}))
        return cls(**d, net=net, task=task)

    def env_config(self, num_agents: int | None = None, num_envs: int | None = None):
        """The training environment (``EnvConfig.for_robot``), or one of other sizes."""
        from ..env import EnvConfig

        return EnvConfig.for_robot(self.robot, num_agents=num_agents or self.num_agents, area_size=self.area_size,
                                   num_obstacles=self.num_obstacles, num_envs=num_envs or self.num_envs,
                                   max_steps=self.episode_steps)  # fmt: skip


def make_command_interface(config: MarlTrainConfig, robot: Robot) -> CommandInterface:
    """The command interface the actor of ``config`` acts on for ``robot`` (``config.interface``, default the
    robot's first)."""
    return make_interface(config.interface or robot.interfaces[0], robot)


def is_marl_checkpoint(path: str | Path) -> bool:
    """Whether ``path`` is a MARL checkpoint directory (it holds ``marl.json``)."""
    return (Path(path) / CONFIG_FILE).is_file()


def read_marl_config(path: str | Path) -> tuple[MarlTrainConfig, dict]:
    """The training configuration of the checkpoint ``path`` and the rest of its ``marl.json`` (``iteration``,
    ``frames``, ``wall_s``, ``lagrange``)."""
    info = json.loads((Path(path) / CONFIG_FILE).read_text())
    return MarlTrainConfig.from_dict(info["config"]), {k: v for k, v in info.items() if k != "config"}


def save_marl(path: str | Path, config: MarlTrainConfig, actor: MarlActor, critic: MarlCritic, lagrange: float,
              **progress) -> None:  # fmt: skip
    """Write the checkpoint ``path`` (weights first, then ``marl.json``, each atomically)."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    tensors = {f"actor.{k}": v.detach().cpu().contiguous() for k, v in actor.state_dict().items()}
    tensors |= {f"critic.{k}": v.detach().cpu().contiguous() for k, v in critic.state_dict().items()}
    tensors["lagrange"] = torch.tensor([float(lagrange)])
    tmp = path / (WEIGHTS_FILE + ".tmp")
    save_file(tensors, str(tmp))
    tmp.replace(path / WEIGHTS_FILE)
    info = {"config": config.to_dict(), "lagrange": float(lagrange), **progress}
    write_text_atomic(path / CONFIG_FILE, json.dumps(info, indent=2) + "\n")


def load_actor(path: str | Path, *, device="cpu", dtype=torch.float32) -> tuple[MarlActor, MarlTrainConfig]:
    """The actor of checkpoint ``path`` (in evaluation mode) and its training configuration."""
    path = Path(path)
    if not is_marl_checkpoint(path):
        raise FileNotFoundError(f"{path} is not a MARL checkpoint (no {CONFIG_FILE})")
    config, _ = read_marl_config(path)
    env = config.env_config(num_agents=1, num_envs=1)
    robot = env.make_robot()
    actor = MarlActor(robot, env.comm_radius, make_command_interface(config, robot), config.net)
    actor = actor.to(device=device, dtype=dtype)
    tensors = load_file(str(path / WEIGHTS_FILE))
    actor.load_state_dict({k[len("actor.") :]: v for k, v in tensors.items() if k.startswith("actor.")})
    return actor.eval(), config
