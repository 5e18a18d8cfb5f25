"""The swarm as a PettingZoo ``ParallelEnv``: one scene, agents ``agent_0`` ... ``agent_<N-1>`` (the optional
``marl`` extra: ``pip install -e '.[marl]'``).

Built as PettingZoo's own environments are::

    from egcbf.env.pettingzoo import parallel_env
    env = parallel_env(robot="quadrotor", num_agents=8, num_obstacles=4)
    observations, infos = env.reset(seed=0)
    observations, rewards, terminations, truncations, infos = env.step(
        {agent: env.action_space(agent).sample() for agent in env.agents})

Each agent's observation is a ``gymnasium.spaces.Dict`` of the layout :mod:`egcbf.env.observations` describes
(``state``, ``goal``, ``neighbours``, ``neighbour_mask``, ``hits``, ``hit_mask``; masks as ``int8`` 0/1), its
action a ``Box`` (the robot's actuator box), its reward and cost those of :class:`egcbf.env.task.SwarmTask`
(``infos[agent]["cost"]`` with the collision masks beside it). Nobody terminates; every agent is truncated after
``max_steps`` steps and then leaves ``agents``. :meth:`SwarmParallelEnv.state` is the global state (every agent's
state and goal, the obstacles), flattened. An action missing from ``step``'s dictionary is an error, never a
silent zero.
"""

from __future__ import annotations

import functools
from typing import Any, ClassVar

import numpy as np
import torch

from .config import EnvConfig
from .task import SwarmTask, TaskConfig

try:
    from gymnasium import spaces
    from pettingzoo import ParallelEnv
except ImportError as err:  # pragma: no cover - exercised by the suite without the extra
    raise ImportError(
        "egcbf.env.pettingzoo needs PettingZoo and Gymnasium, the optional `marl` extra: pip install -e '.[marl]'"
    ) from err

__all__ = ["SwarmParallelEnv", "parallel_env"]


def parallel_env(robot: str = "quadrotor", num_agents: int = 8, **options) -> SwarmParallelEnv:
    """A :class:`SwarmParallelEnv` of ``num_agents`` agents of ``robot``; ``options`` are those of
    :class:`SwarmParallelEnv` (``task``, ``dtype``, ``device``, ``render_mode``) and any :class:`EnvConfig` field
    (``area_size``, ``num_obstacles``, ``max_steps``, ...; the robot's own defaults otherwise)."""
    return SwarmParallelEnv(robot=robot, num_agents=num_agents, **options)


class SwarmParallelEnv(ParallelEnv):
    """One scene of ``num_agents`` agents as a PettingZoo ``ParallelEnv`` (module doc). ``dtype`` is that of the
    simulation and of the observations (``float32`` by default; ``torch.float64`` for exact comparisons)."""

    metadata: ClassVar[dict] = {"name": "egcbf_swarm_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(self, robot: str = "quadrotor", num_agents: int = 8, *, task: TaskConfig | None = None,
                 dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu", render_mode: str | None = None,
                 **env_options: Any):  # fmt: skip
        if render_mode is not None:
            raise ValueError(f"render_mode {render_mode!r} is not supported (egcbf's renderer: egcbf.viz)")
        if env_options.get("num_envs", 1) != 1:
            raise ValueError("a PettingZoo environment is one scene (num_envs = 1); egcbf.env.torchrl batches scenes")
        config = EnvConfig.for_robot(robot, num_agents=num_agents, **env_options)
        self.task = SwarmTask(config, task, device=device, dtype=dtype)
        self.render_mode = None
        self.possible_agents = [f"agent_{i}" for i in range(config.num_agents)]
        self.agents: list[str] = []
        self._np_dtype = torch.empty((), dtype=dtype).numpy().dtype
        lo, hi = self.task.control_bounds()
        low, high = (b.cpu().numpy().astype(self._np_dtype) for b in (lo, hi))
        self._action_space = spaces.Box(low, high, dtype=self._np_dtype)
        fields = {}
        for key, shape in self.task.layout.shapes().items():
            if self.task.layout.is_mask(key):
                fields[key] = spaces.Box(0, 1, shape, dtype=np.int8)
            else:
                fields[key] = spaces.Box(-np.inf, np.inf, shape, dtype=self._np_dtype)
        self._observation_space = spaces.Dict(fields)
        self._seed_rng = np.random.default_rng()
        self._observations: dict[str, np.ndarray] = {}

    @property
    def config(self) -> EnvConfig:
        return self.task.config

    @functools.cache  # noqa: B019 - the same space object per agent, as PettingZoo requires
    def observation_space(self, agent: str) -> spaces.Dict:
        self._index(agent)
        return self._observation_space

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Box:
        self._index(agent)
        return self._action_space

    @functools.cached_property
    def state_space(self) -> spaces.Box:
        return spaces.Box(-np.inf, np.inf, (self._state_size(),), dtype=self._np_dtype)

    def _index(self, agent: str) -> int:
        try:
            return self.possible_agents.index(agent)
        except ValueError:
            raise KeyError(
                f"no agent {agent!r} (agents are agent_0 ... agent_{len(self.possible_agents) - 1})"
            ) from None

    def _state_size(self) -> int:
        c, robot = self.config, self.task.robot
        obstacle = robot.dim + 1 + (4 if c.obstacle_shape == "rectangle" else 0)  # centre, radius, box
        return c.num_agents * (robot.state_dim + robot.dim) + c.num_obstacles * obstacle

    def _split(self, obs: dict[str, torch.Tensor]) -> dict[str, dict[str, np.ndarray]]:
        arrays = {}
        for key, value in obs.items():
            a = value[0].detach().cpu().numpy()
            arrays[key] = a.astype(np.int8) if self.task.layout.is_mask(key) else a.astype(self._np_dtype, copy=False)
        return {agent: {key: a[i] for key, a in arrays.items()} for i, agent in enumerate(self.possible_agents)}

    def reset(self, seed: int | None = None, options: dict | None = None):
        """New episode: from ``seed`` when given (the same seed, the same scene, on any device); else from a seed
        drawn from the generator the last seeded reset set up."""
        if seed is not None:
            self._seed_rng = np.random.default_rng(seed)
            episode_seed = int(seed)
        else:
            episode_seed = int(self._seed_rng.integers(2**31 - 1))
        self.agents = list(self.possible_agents)
        obs = self._split(self.task.reset(episode_seed))
        return obs, {agent: {} for agent in self.agents}

    def step(self, actions: dict[str, Any]):
        if not self.agents:
            raise RuntimeError("step after every agent has left (the episode was truncated); call reset()")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"step needs an action for every live agent; missing: {', '.join(missing[:5])}"
                             + (" ..." if len(missing) > 5 else ""))  # fmt: skip
        env = self.task.env
        rows = [torch.as_tensor(np.asarray(actions[a]), dtype=env.dtype) for a in self.possible_agents]
        k = self.task.robot.control_dim
        for agent, row in zip(self.possible_agents, rows):
            if tuple(row.shape) != (k,):
                raise ValueError(f"the action of {agent} must have shape ({k},), got {tuple(row.shape)}")
        out = self.task.step(torch.stack(rows)[None].to(env.device))
        obs = self._split(out.observation)
        reward = out.reward[0].cpu().tolist()
        cost = out.cost[0].cpu().tolist()
        masks = {key: m[0].cpu().tolist() for key, m in out.info.items()}
        truncated = bool(out.truncated[0])
        agents = self.possible_agents
        rewards = {a: float(reward[i]) for i, a in enumerate(agents)}
        infos = {a: {"cost": float(cost[i]), **{key: bool(v[i]) for key, v in masks.items()}} for i, a in
                 enumerate(agents)}  # fmt: skip
        terminations = dict.fromkeys(agents, False)
        truncations = dict.fromkeys(agents, truncated)
        if truncated:
            self.agents = []
        return obs, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        """The global state ``(state_space.shape)``: every agent's state, then every goal, then the obstacles'
        centres, radii and (rectangles) boxes (``Obstacles``: half sides, orientation), flattened."""
        s = self.task.state
        if s is None:
            raise RuntimeError("state() before reset()")
        o = s.obstacles
        parts = [s.x[0], s.goals[0], o.centers[0], o.radii[0], o.packed_boxes[0]]
        return (
            torch.cat([p.reshape(-1).to(s.x.dtype) for p in parts])
            .detach()
            .cpu()
            .numpy()
            .astype(self._np_dtype, copy=False)
        )

    def render(self) -> None:
        return None

    def close(self) -> None:
        return None
