"""Evaluation: run a controller on batches of episodes and compute the paper's metrics.

Every episode ``e`` of a swarm size ``N`` is sampled from its own seed ``episode_seed(seed, N, e)``, so what an
episode is does not depend on how episodes are batched; its trajectory does up to floating-point rounding (batched
matrix products round differently, and a closed loop can amplify that over 256 steps: millimetres, measured), so
rerun a cell with the same ``batch`` to reproduce it bit for bit. Episodes are simulated ``batch`` at a time
(vectorized over environments and agents).

A controller is any callable ``controller(state, config) -> (u, info)`` with ``u`` ``(B, N, 4)`` and ``info`` a
dict that may hold ``qp_ms`` (solve time of this step, ms), ``num_slack`` / ``num_failed`` (QP counts), ``u_ref``
(the nominal control it started from; computed here if absent), and for a run-time filter ``num_active`` /
``num_agents`` (agents whose command it changed, of how many: the row's ``filter_active``).

``low_level`` (:data:`LOW_LEVELS`) is what turns a controller's command into rotor thrusts: ``"attitude"`` (default)
applies ``u``, which for the acceleration interface and the run-time filters is our attitude loop tracking their
acceleration command; ``"setpoint"`` flies that command (``info["accel_command"]``, world frame, m/s^2) as a
full-state setpoint through the firmware-like tracker (:func:`egcbf.env.swarm.advance`,
:mod:`egcbf.robots.quadrotor.setpoint`) instead: the substitution a Crazyflie makes. A controller without an
acceleration command (the torque interface, the hand-crafted QPs' body controls) cannot be flown so, and says so.

``on_step(config, state, u, info)`` (:data:`StepCallback`) watches an episode batch without changing it: called
before every step with the true state ``(B, N, ...)``, the control ``u`` the controller chose and its ``info``, and
once after the last step with the final state and ``u = info = None`` (``egcbf eval --record``, :mod:`egcbf.ros`).
"""

from __future__ import annotations

import dataclasses
import numbers
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor
from tqdm.auto import tqdm

from ..env import EnvConfig, SwarmEnv, SwarmState
from ..env.obstacles import Obstacles
from ..faults import FaultConfig, FaultProcess
from ..faults.sensing import unread_faults
from ..robots import DEFAULT_ROBOT
from .metrics import EpisodeStats, summarize

__all__ = [
    "LOW_LEVELS",
    "MAX_AGENTS_PER_BATCH",
    "PER_EPISODE_KEYS",
    "EpisodeRecord",
    "StepCallback",
    "concat_states",
    "episode_batch",
    "episode_seed",
    "evaluate",
    "fault_support_error",
    "run_episodes",
]

Controller = Callable[[SwarmState, EnvConfig], tuple[Tensor, dict]]
#: ``on_step(config, state, u, info)`` (module doc): ``u`` and ``info`` are ``None`` at the final state
StepCallback = Callable[[EnvConfig, SwarmState, Tensor | None, dict | None], None]


#: episodes of one swarm size are simulated together, up to this many agents in all (``batch`` unset)
MAX_AGENTS_PER_BATCH = 4096

#: how a controller's command reaches the rotors (module doc): our attitude loop's ``u``, or the firmware-like
#: setpoint tracker flying the acceleration command
LOW_LEVELS = ("attitude", "setpoint")

#: the per-episode values a row keeps (``row["per_episode"][key]``, one per episode, in episode order)
PER_EPISODE_KEYS = ("safe_rate", "reach_rate", "success_rate", "cost", "reward")


def episode_batch(num_agents: int, episodes: int, max_agents_per_batch: int = MAX_AGENTS_PER_BATCH) -> int:
    """How many of ``episodes`` episodes of ``num_agents`` agents :func:`evaluate` simulates together."""
    return max(1, min(episodes, max_agents_per_batch // num_agents))


def episode_seed(seed: int, num_agents: int, episode: int) -> int:
    """The reset seed of episode ``episode`` for swarm size ``num_agents`` (independent of batching)."""
    return (int(seed) * 1_000_003 + int(num_agents) * 10_007 + int(episode)) % (2**62)


def concat_states(states: Sequence[SwarmState]) -> SwarmState:
    """Stack single- or multi-environment states along the environment dimension."""
    obs = Obstacles.cat([s.obstacles for s in states])
    x, goals = torch.cat([s.x for s in states]), torch.cat([s.goals for s in states])
    return SwarmState(x, goals, obs, states[0].t, states[0].robot)


@dataclass
class EpisodeRecord:
    """Trajectory of the first episode of a batch, for rendering (CPU tensors)."""

    positions: list[Tensor] = field(default_factory=list)  # T x (N, 3)
    collided: list[Tensor] = field(default_factory=list)  # T x (N,)
    goals: Tensor | None = None
    centers: Tensor | None = None
    radii: Tensor | None = None
    boxes: Tensor | None = None  # (K, 4): rectangle obstacles (egcbf.env.Obstacles.boxes); None: round


def _new_timing() -> dict:
    """The step times and QP / filter counts :func:`run_episodes` collects and :func:`evaluate` pools."""
    return {"step_ms": [], "qp_ms": [], "num_slack": 0, "num_failed": 0, "num_active": 0, "num_filtered": 0}


def fault_support_error(controller, faults: FaultConfig, name: str | None = None) -> str | None:
    """Why ``controller`` cannot be evaluated under ``faults`` (``None``: it can), for the error of
    :func:`run_episodes` and of ``egcbf eval --faults``; ``name``: how to call the controller (default: its
    ``name`` attribute).

    Message and LiDAR faults reach a controller only through what it perceives (``state.sensing``,
    :class:`egcbf.faults.Sensing`); one that reads its neighbours or obstacles from the state would silently ignore
    them, so it must declare the channels it reads (``reads_sensing``, :func:`egcbf.faults.sensing.unread_faults`).
    """
    unread = unread_faults(controller, faults)
    if not unread:
        return None
    name = name or getattr(controller, "name", type(controller).__name__)
    listed = ", ".join(f"{k}={getattr(faults, k):g}" for k in unread)
    return (
        f"{listed} reach a controller only through what its agents perceive (egcbf.faults.Sensing); {name!r} does "
        "not read them (it reads its neighbours or obstacles from the state). The learned policies read messages and "
        "LiDAR, alone and behind the cbf or prior filter; the dcbf controller and the dcbf filter read the messages "
        f"only (their obstacle rows read the obstacle map). Evaluate {name!r} without {', '.join(unread)}."
    )


def _require_fault_support(controller, faults: FaultConfig) -> None:
    """Raise ``ValueError`` if ``controller`` would ignore some of ``faults`` (:func:`fault_support_error`)."""
    why = fault_support_error(controller, faults)
    if why is not None:
        raise ValueError(f"faults {faults.spec()!r}: {why}")


def _check_low_level(low_level: str, config: EnvConfig, faults: FaultConfig | None) -> None:
    """Raise ``ValueError`` for a ``low_level`` that is unknown or that cannot fly this robot or these faults."""
    if low_level not in LOW_LEVELS:
        raise ValueError(f"low_level must be one of {LOW_LEVELS}, got {low_level!r}")
    if low_level == "attitude":
        return
    if not config.make_robot().flies_setpoints:
        raise ValueError(f"low_level 'setpoint' flies a robot's firmware-like setpoint tracker (the quadrotor's: the "
                         f"Crazyflie's Mellinger controller); the {config.robot} has none")  # fmt: skip
    if faults is not None and not faults.is_null:
        raise ValueError("low_level 'setpoint' with faults: the faults corrupt the body control u, which the "
                         "setpoint tracker does not apply; evaluate it without faults")  # fmt: skip


def _setpoint(controller, info: dict) -> Tensor:
    """The acceleration command a setpoint-flying low level tracks (``info["accel_command"]``), or ``ValueError``."""
    a = info.get("accel_command")
    if a is None:
        name = getattr(controller, "name", type(controller).__name__)
        raise ValueError(
            f"low_level 'setpoint' flies the controller's world acceleration command (info['accel_command']); "
            f"{name!r} gives none (its command is not an acceleration, e.g. the torque interface, or it returns body "
            "controls only): evaluate it with low_level 'attitude'"
        )
    return a


def run_episodes(
    controller: Controller,
    config: EnvConfig,
    seeds: Sequence[int],
    *,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    record: bool = False,
    progress: tqdm | None = None,
    faults: FaultConfig | None = None,
    fault_rotation: Tensor | None = None,
    on_step: StepCallback | None = None,
    low_level: str = "attitude",
) -> tuple[EpisodeStats, dict, EpisodeRecord | None]:
    """Simulate ``len(seeds)`` episodes together; returns their stats, timing lists and (optionally) the record
    of the first episode.

    ``faults`` (:mod:`egcbf.faults`; ``None`` or all zero: the perfect world, bit for bit): the controller sees the
    agents' corrupted perception, its commands reach the rotors corrupted, wind pushes the agents; the metrics read
    the true states and count the cooperative agents only. ``fault_rotation`` rotates the faults' world-frame draws
    (:class:`egcbf.faults.FaultProcess`; the equivariance tests). ``on_step``: see the module doc (outside the
    timed step). ``low_level``: ``"attitude"`` or ``"setpoint"`` (module doc)."""
    seeds = list(seeds)
    if not seeds:
        raise ValueError("run_episodes: seeds is empty; give at least one episode seed")
    _check_low_level(low_level, config, faults)
    single = dataclasses.replace(config, num_envs=1)
    env1 = SwarmEnv(single, device=device, dtype=dtype)
    state = concat_states([env1.reset(s) for s in seeds])
    env = SwarmEnv(dataclasses.replace(config, num_envs=len(seeds)), device=device, dtype=dtype)
    robot = env.robot
    process = None
    if faults is not None and not faults.is_null:
        process = FaultProcess(faults, env.config, robot, seeds, device=device, dtype=dtype, rotation=fault_rotation)
        _require_fault_support(controller, faults)
    counted = None if process is None or not bool(process.noncoop.any()) else ~process.noncoop
    stats = EpisodeStats(len(seeds), config.num_agents, device=device, counted=counted)
    timing = _new_timing()
    rec = None
    if record:
        obs = state.obstacles
        rec = EpisodeRecord(
            goals=state.goals[0].cpu(), centers=obs.centers[0].cpu(), radii=obs.radii[0].cpu(),
            boxes=None if obs.boxes is None else obs.boxes[0].cpu(),
        )  # fmt: skip
        rec.positions.append(state.positions[0].detach().cpu().clone())
        rec.collided.append(torch.zeros(config.num_agents, dtype=torch.bool))
    for _ in range(config.max_steps):
        t0 = time.perf_counter()
        seen = state if process is None else process.observe(state)
        u, info = controller(seen, env.config)
        if on_step is not None:
            t_watch = time.perf_counter()
            on_step(env.config, state, u, info)
            t0 += time.perf_counter() - t_watch  # the step time is the controller's and the simulator's
        u_ref = info.get("u_ref")
        if u_ref is None:  # the reward compares u with the nominal control at the same state
            u_ref = robot.nominal_control(seen.x, seen.goals)
        if process is not None:
            u = process.actuate(u, state)
        state, step_info = env.step(state, u, _setpoint(controller, info) if low_level == "setpoint" else None)
        if process is not None and process.pushes:
            state = process.push(state)
            step_info = env.info(state, u=step_info.u)
        timing["step_ms"].append(1e3 * (time.perf_counter() - t0))
        stats.update(step_info, u=step_info.u, u_ref=u_ref.to(step_info.u.dtype))
        if "qp_ms" in info:
            timing["qp_ms"].append(float(info["qp_ms"]))
        timing["num_slack"] += int(info.get("num_slack", 0))
        timing["num_failed"] += int(info.get("num_failed", 0))
        timing["num_active"] += int(info.get("num_active", 0))
        timing["num_filtered"] += int(info.get("num_agents", 0))
        if rec is not None:
            rec.positions.append(state.positions[0].detach().cpu().clone())
            rec.collided.append(step_info.collision[0].detach().cpu().clone())
        if progress is not None:
            progress.update(len(seeds))
    if on_step is not None:
        on_step(env.config, state, None, None)
    return stats, timing, rec


def evaluate(
    make_controller: Callable[[EnvConfig], Controller],
    num_agents: Sequence[int],
    *,
    area_size: float = 4.0,
    num_obstacles: int = 0,
    episodes: int = 50,
    seed: int = 0,
    batch: int | None = None,
    max_agents_per_batch: int = MAX_AGENTS_PER_BATCH,
    max_steps: int | None = None,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    record: bool = False,
    show_progress: bool = True,
    env_overrides: dict | None = None,
    on_size: Callable[[list[dict], EpisodeRecord | None], None] | None = None,
    robot: str = DEFAULT_ROBOT,
    faults: FaultConfig | None = None,
    on_step: StepCallback | None = None,
    low_level: str = "attitude",
) -> tuple[list[dict], dict[int, EpisodeRecord]]:
    """Evaluate a controller at each swarm size; returns one metrics row per size (see ``docs/metrics.md``; its
    ``per_episode`` holds the lists of :data:`PER_EPISODE_KEYS` over the episodes, in episode order) and the recorded
    first episode per size (if ``record``).

    ``on_size(rows, record)`` is called as soon as each size is finished, with the rows so far and that size's
    record (or ``None``): the CLI writes its results there, so that a later failure loses no finished size.
    ``robot`` (:mod:`egcbf.robots`) sets the environment's defaults (:meth:`EnvConfig.for_robot`). ``faults``
    (:mod:`egcbf.faults`): evaluate under these faults (see :func:`run_episodes`); the rows then hold ``faults``, the
    spec string. ``on_step`` (module doc) watches the first batch of episodes of each size (its first episode is
    environment 0 of the states it is given). ``low_level`` (module doc): ``"attitude"`` or ``"setpoint"``; the rows
    of ``"setpoint"`` hold ``low_level``.
    """
    if not callable(make_controller):
        raise TypeError(
            "evaluate: make_controller must be a callable EnvConfig -> controller (e.g. lambda cfg: controller), got "
            f"{type(make_controller).__name__}"
        )
    for name, value in (("seed", seed), ("episodes", episodes)):  # a float would be truncated silently below
        if not isinstance(value, numbers.Integral) or isinstance(value, bool):
            raise TypeError(f"evaluate: {name} must be an integer, got {value!r}")
    if isinstance(num_agents, (int, str)) or not all(
        isinstance(n, numbers.Integral) and not isinstance(n, bool) for n in num_agents
    ):
        raise TypeError(f"evaluate: num_agents must be a sequence of integers (e.g. [8, 16]), got {num_agents!r}")
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if batch is not None and batch < 1:
        raise ValueError(f"batch must be >= 1 or None, got {batch}")
    rows, records = [], {}
    for n in num_agents:
        overrides = dict(env_overrides or {})
        if max_steps is not None:
            overrides["max_steps"] = max_steps
        config = EnvConfig.for_robot(robot, num_agents=n, area_size=area_size, num_obstacles=num_obstacles, **overrides)
        controller = make_controller(config)
        b = batch or episode_batch(n, episodes, max_agents_per_batch)
        seeds = [episode_seed(seed, n, e) for e in range(episodes)]
        per_episode = []
        timing = _new_timing()
        bar = tqdm(
            total=episodes * config.max_steps, desc=f"N={n}", unit="step", disable=not show_progress, leave=False
        )
        for k in range(0, episodes, b):
            chunk = seeds[k : k + b]
            stats, t, rec = run_episodes(
                controller,
                config,
                chunk,
                device=device,
                dtype=dtype,
                record=record and k == 0,
                progress=bar,
                faults=faults,
                on_step=on_step if k == 0 else None,
                low_level=low_level,
            )
            per_episode.append(stats.per_episode())
            for key in ("step_ms", "qp_ms"):
                # per-episode time: a batch step serves len(chunk) episodes at once
                timing[key].extend(v / len(chunk) for v in t[key])
            for key in ("num_slack", "num_failed", "num_active", "num_filtered"):
                timing[key] += t[key]
            if rec is not None:
                records[n] = rec
        bar.close()
        pooled = {k: torch.cat([p[k] for p in per_episode]) for k in per_episode[0]}
        row = summarize(pooled, num_agents=n)
        # each episode's own values, in episode order: what a confidence interval over episodes resamples
        row["per_episode"] = {k: pooled[k].double().tolist() for k in PER_EPISODE_KEYS}
        row["step_ms_median"] = statistics.median(timing["step_ms"])
        if faults is not None and not faults.is_null:
            row["faults"] = faults.spec()
        if low_level != "attitude":
            row["low_level"] = low_level
        if timing["qp_ms"] and max(timing["qp_ms"]) > 0:  # controllers without a QP report 0
            row["qp_ms_median"] = statistics.median(timing["qp_ms"])
            row["qp_slack_steps"] = timing["num_slack"]
            row["qp_failed"] = timing["num_failed"]
        if timing["num_filtered"]:  # a run-time filter: the fraction of agent-steps whose command it changed
            row["filter_active"] = timing["num_active"] / timing["num_filtered"]
        rows.append(row)
        if on_size is not None:
            on_size(list(rows), records.get(n))
    return rows, records
