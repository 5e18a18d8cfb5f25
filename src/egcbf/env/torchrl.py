"""The swarm as a native batched TorchRL environment (the optional ``marl`` extra: ``pip install -e '.[marl]'``).

:class:`SwarmTorchRLEnv` is an ``EnvBase`` with ``batch_size = [B]``: ``B`` scenes of ``N`` agents step as one
tensor program (:class:`egcbf.env.task.SwarmTask`), with nothing split into per-agent dictionaries. Keys (shapes
with the batch):

==========================================  ====================  ==============================================
key                                         shape                 spec
==========================================  ====================  ==============================================
``("agents", "observation", <key>)``        ``(B, N, ...)``       :mod:`egcbf.env.observations` (masks: bool)
``("agents", "action")``                    ``(B, N, k)``         ``Bounded``: the robot's actuator box
``("agents", "reward")``                    ``(B, N, 1)``         :class:`~egcbf.env.task.SwarmTask`'s reward
``("agents", "info", "cost")``              ``(B, N, 1)``         1 for a collision (``collision_cost``)
``("agents", "info", <mask>)``              ``(B, N, 1)`` bool    ``collision``, ``agent_collision``,
                                                                  ``obstacle_collision``, ``unsafe``, ``reached``
``"done"``, ``"terminated"``, ``"truncated"``  ``(B, 1)`` bool    truncation after ``max_steps`` (never terminated)
==========================================  ====================  ==============================================

Every scene starts and ends its episode together (the simulator steps all of them in lock-step): a reset resets
all ``B`` (a partial ``"_reset"`` mask is refused, never half-honoured). Episode ``e`` after ``set_seed(s)`` is
drawn from seed ``s + e``, so a seeded run is reproducible and its episodes differ.

::

    env = SwarmTorchRLEnv(EnvConfig.for_robot("quadrotor", num_agents=64, num_envs=8))
    td = env.rollout(256, policy)     # policy: a TensorDictModule writing ("agents", "action")
"""

from __future__ import annotations

import torch

from .config import EnvConfig
from .task import INFO_KEYS, SwarmTask, TaskConfig

try:
    from tensordict import TensorDict, TensorDictBase
    from torchrl.data import Binary, Bounded, Composite, Unbounded
    from torchrl.envs import EnvBase
except ImportError as err:  # pragma: no cover - exercised by the suite without the extra
    raise ImportError(
        "egcbf.env.torchrl needs TorchRL and TensorDict, the optional `marl` extra: pip install -e '.[marl]'"
    ) from err

__all__ = ["SwarmTorchRLEnv"]


class SwarmTorchRLEnv(EnvBase):
    """``B = config.num_envs`` swarms of ``N = config.num_agents`` agents as a batched TorchRL environment (module
    doc). ``dtype`` is the simulation's and the observations' (``float32`` by default); ``seed`` the first
    episode's seed until :meth:`set_seed`."""

    batch_locked = True

    def __init__(self, config: EnvConfig, task: TaskConfig | None = None, *, device: str | torch.device = "cpu",
                 dtype: torch.dtype = torch.float32, seed: int = 0):  # fmt: skip
        self.task = SwarmTask(config, task, device=device, dtype=dtype)
        b, n = config.num_envs, config.num_agents
        super().__init__(device=torch.device(device), batch_size=torch.Size([b]))
        self._next_seed = int(seed)
        layout = self.task.layout
        observation = {}
        for key, shape in layout.shapes().items():
            full = (b, n, *shape)
            if layout.is_mask(key):
                observation[key] = Binary(n=shape[-1], shape=full, dtype=torch.bool, device=self.device)
            else:
                observation[key] = Unbounded(shape=full, dtype=dtype, device=self.device)
        info = {"cost": Unbounded(shape=(b, n, 1), dtype=dtype, device=self.device)}
        for key in INFO_KEYS:
            info[key] = Binary(n=1, shape=(b, n, 1), dtype=torch.bool, device=self.device)
        agents = Composite(
            observation=Composite(observation, shape=(b, n), device=self.device),
            info=Composite(info, shape=(b, n), device=self.device),
            shape=(b, n), device=self.device,
        )  # fmt: skip
        self.observation_spec = Composite(agents=agents, shape=(b,), device=self.device)
        lo, hi = self.task.control_bounds()
        k = self.task.robot.control_dim
        action = Bounded(low=lo.expand(b, n, k), high=hi.expand(b, n, k), shape=(b, n, k), dtype=dtype,
                         device=self.device)  # fmt: skip
        self.action_spec = Composite(agents=Composite(action=action, shape=(b, n)), shape=(b,), device=self.device)
        reward = Unbounded(shape=(b, n, 1), dtype=dtype, device=self.device)
        self.reward_spec = Composite(agents=Composite(reward=reward, shape=(b, n)), shape=(b,), device=self.device)
        flag = {name: Binary(n=1, shape=(b, 1), dtype=torch.bool, device=self.device)
                for name in ("done", "terminated", "truncated")}  # fmt: skip
        self.done_spec = Composite(flag, shape=(b,), device=self.device)

    @property
    def config(self) -> EnvConfig:
        return self.task.config

    def _set_seed(self, seed: int | None) -> None:
        self._next_seed = 0 if seed is None else int(seed)

    def _pack(self, observation: dict, info: dict | None = None, cost: torch.Tensor | None = None) -> dict:
        b = self.batch_size[0]
        n = self.config.num_agents
        agents = {"observation": TensorDict(observation, batch_size=(b, n), device=self.device)}
        if info is None:  # a reset: no step happened, so no cost and no collision of a step
            zero = torch.zeros(b, n, 1, dtype=self.task.env.dtype, device=self.device)
            info = {key: torch.zeros(b, n, 1, dtype=torch.bool, device=self.device) for key in INFO_KEYS}
            info["cost"] = zero
        else:
            info = {key: value[..., None] for key, value in info.items()} | {"cost": cost[..., None]}
        agents["info"] = TensorDict(info, batch_size=(b, n), device=self.device)
        return {"agents": TensorDict(agents, batch_size=(b, n), device=self.device)}

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset")
            if bool(mask.any()) and not bool(mask.all()):
                raise ValueError("SwarmTorchRLEnv resets all its scenes together (they step in lock-step); got a "
                                 "partial '_reset' mask")  # fmt: skip
        seed, self._next_seed = self._next_seed, self._next_seed + 1
        obs = self.task.reset(seed)
        b = self.batch_size[0]
        out = self._pack(obs)
        false = torch.zeros(b, 1, dtype=torch.bool, device=self.device)
        out.update(done=false, terminated=false.clone(), truncated=false.clone())
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        u = tensordict.get(("agents", "action"))
        out = self.task.step(u.to(device=self.task.env.device, dtype=self.task.env.dtype))
        packed = self._pack(out.observation, out.info, out.cost)
        packed["agents"].set("reward", out.reward[..., None])
        truncated = out.truncated[:, None]
        packed.update(done=truncated.clone(), terminated=torch.zeros_like(truncated), truncated=truncated)
        return TensorDict(packed, batch_size=self.batch_size, device=self.device)
