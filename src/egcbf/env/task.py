"""The swarm as a multi-agent learning task: per-agent observations, rewards and costs on top of :class:`SwarmEnv`.

:class:`SwarmTask` is the one implementation both outside interfaces wrap (``egcbf.env.pettingzoo``: one scene,
NumPy dictionaries per agent; ``egcbf.env.torchrl``: ``B`` scenes as one TensorDict). It is batched like the
simulator (``B`` environments of ``N`` agents, torch tensors) and adds only what a learner needs:

* **observation**: :func:`egcbf.env.observations.agent_observations` (each agent's own state and goal, its ``K``
  nearest neighbours' states and its LiDAR hits, with masks; world frame);
* **action**: the robot's control ``u`` in its actuator box (``Robot.control_bounds``); the simulator clips it;
* **reward** of agent ``i`` for a step from ``x`` to ``x'`` with the applied control ``u``::

      r_i = - deviation_weight * mean_j ((u_ij - n_ij) / w_j)^2  +  progress_weight * (|p_i - g_i| - |p'_i - g_i|) / r

  with ``n = Robot.nominal_control(x, goals)`` (the nominal controller's command at ``x``), ``w`` the half-widths of
  the actuator box, ``r`` the agent radius. The first term is the CBF literature's objective (stay close to the
  nominal command: a policy that follows it exactly scores 0 there); the second pays progress toward the goal
  in agent radii, so that a policy that never moves is not optimal;
* **cost** ``c_i = 1`` if agent ``i`` collides (with an agent or an obstacle) in ``x'``, else 0: the constraint
  of a safe-RL method (keep the expected cost rate below a budget). ``info`` also holds the collision parts,
  the training labels' ``unsafe`` mask and ``reached``;
* **episode end**: no agent ever terminates (a collision is a cost, as in GCBF+'s evaluation); every environment
  is truncated together after ``EnvConfig.max_steps`` steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .config import EnvConfig
from .observations import NeighbourList, ObservationLayout, agent_observations
from .swarm import StepInfo, SwarmEnv, SwarmState

__all__ = ["SwarmTask", "TaskConfig", "TaskStep"]


@dataclass(frozen=True)
class TaskConfig:
    """The learning task's settings (module doc): ``max_neighbours`` ``K`` rows of the observation, the reward's
    weights, the cost of a collision; ``neighbour_skin``: the Verlet skin of the neighbour search in communication
    radii (:class:`~egcbf.env.observations.NeighbourList`: a speed setting only; 0 searches anew every step)."""

    max_neighbours: int = 16
    deviation_weight: float = 1.0
    progress_weight: float = 1.0
    collision_cost: float = 1.0
    neighbour_skin: float = 0.2

    def __post_init__(self) -> None:
        for name in ("deviation_weight", "progress_weight", "collision_cost", "neighbour_skin"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0 or v == float("inf"):
                raise ValueError(f"TaskConfig.{name} must be a finite number >= 0, got {v!r}")


@dataclass
class TaskStep:
    """What :meth:`SwarmTask.step` returns: ``observation`` (key -> ``(B, N, ...)``), ``reward`` and ``cost``
    ``(B, N)``, ``truncated`` ``(B,)`` bool, ``info`` (key -> ``(B, N)`` bool: ``collision``,
    ``agent_collision``, ``obstacle_collision``, ``unsafe``, ``reached``), and the simulator's ``state``."""

    observation: dict[str, Tensor]
    reward: Tensor
    cost: Tensor
    truncated: Tensor
    info: dict[str, Tensor]
    state: SwarmState


#: the masks of :class:`StepInfo` a step reports in ``info``
INFO_KEYS = ("collision", "agent_collision", "obstacle_collision", "unsafe", "reached")


class SwarmTask:
    """``B`` swarms of ``N`` agents as a multi-agent task (module doc).

    ``task = SwarmTask(EnvConfig(num_agents=8), TaskConfig())``; ``obs = task.reset(seed)``;
    ``out = task.step(u)`` with ``u`` ``(B, N, control_dim)``. The state lives in :attr:`state`.
    """

    def __init__(self, config: EnvConfig, task: TaskConfig | None = None, *, device=None, dtype=None):
        if task is not None and not isinstance(task, TaskConfig):
            raise TypeError(f"task must be a TaskConfig, got {type(task).__name__}")
        self.env = SwarmEnv(config, device=device, dtype=dtype)
        self.task = task or TaskConfig()
        self.layout = ObservationLayout.of(config, self.task.max_neighbours)
        self.neighbours = NeighbourList(config.comm_radius, self.task.neighbour_skin * config.comm_radius)
        self.state: SwarmState | None = None

    @property
    def config(self) -> EnvConfig:
        return self.env.config

    @property
    def robot(self):
        return self.env.robot

    def control_bounds(self) -> tuple[Tensor, Tensor]:
        """``lo, hi`` ``(control_dim,)`` of the action, in the task's dtype and device."""
        like = torch.zeros((), dtype=self.env.dtype, device=self.env.device)
        return self.robot.control_bounds(like)

    def observe(self, state: SwarmState) -> dict[str, Tensor]:
        """The observations of ``state`` (:func:`agent_observations`)."""
        scan = self.env.lidar(state)
        return agent_observations(state.x, state.goals, state.positions, scan, self.config.comm_radius,
                                  self.task.max_neighbours, self.neighbours)  # fmt: skip

    def reset(self, seed: int) -> dict[str, Tensor]:
        """New episodes from ``seed`` (:meth:`SwarmEnv.reset`); their observations."""
        self.state = self.env.reset(seed)
        self.neighbours.reset()
        return self.observe(self.state)

    def step(self, u: Tensor) -> TaskStep:
        """One step of every environment with the controls ``u`` ``(B, N, control_dim)``."""
        if self.state is None:
            raise RuntimeError("SwarmTask.step before reset: call reset(seed) first")
        if self.state.t >= self.config.max_steps:
            raise RuntimeError(f"the episode has ended (max_steps = {self.config.max_steps}); call reset(seed)")
        before = self.state
        nominal = None
        if self.task.deviation_weight > 0:  # clipped: the command the simulator would apply
            nominal = self.robot.clip_control(self.robot.nominal_control(before.x, before.goals))
        after, applied = self.env.transition(before, u)
        self.state = after
        observation = self.observe(after)
        info = self.env.info(after, u=applied, agent_pairs=self._unsafe_pairs())
        reward, cost = self.reward_and_cost(before, after, info, nominal)
        masks = {key: getattr(info, key) for key in INFO_KEYS}
        return TaskStep(observation, reward, cost, info.done, masks, after)

    def _unsafe_pairs(self) -> tuple[Tensor, Tensor] | None:
        """The agent pairs of the last observation that may be closer than the unsafe distance (the neighbour
        search's: :meth:`NeighbourList.pairs_within`), for the step's masks; ``None`` (the masks search) when that
        distance is not well inside the communication radius."""
        c = self.config
        unsafe = c.unsafe_agent_distance * c.agent_radius
        if not unsafe**2 * (1 + 1e-3) < self.neighbours.radius**2:
            return None
        return self.neighbours.pairs_within(unsafe)

    def reward_and_cost(
        self, before: SwarmState, after: SwarmState, info: StepInfo, nominal: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        """The reward and cost ``(B, N)`` of the step ``before -> after`` (module doc); ``info.u`` is the control
        applied, ``nominal`` the nominal command at ``before`` (``None`` when ``deviation_weight`` is 0)."""
        t = self.task
        lo, hi = self.control_bounds()
        reward = torch.zeros(before.x.shape[:2], dtype=before.x.dtype, device=before.x.device)
        if nominal is not None:
            half = ((hi - lo) / 2).to(before.x.dtype)
            reward = reward - t.deviation_weight * ((info.u - nominal) / half).square().mean(-1)
        if t.progress_weight > 0:
            gap_before = torch.linalg.vector_norm(before.positions - before.goals, dim=-1)
            gap_after = torch.linalg.vector_norm(after.positions - after.goals, dim=-1)
            reward = reward + t.progress_weight * (gap_before - gap_after) / self.config.agent_radius
        cost = info.collision.to(before.x.dtype) * t.collision_cost
        return reward, cost
