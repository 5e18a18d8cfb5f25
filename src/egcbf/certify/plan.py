"""Which rollouts ``egcbf certify`` runs (its cells), what each depends on, and running one.

A cell is one controller on one setting (robot, ``N``, arena, obstacles, episodes from the evaluation seed) whose
rollouts are recorded once and scored against several barriers: the learned CBF of the checkpoint whose policy runs
(and, on the quadrotor, the ``dcbf`` filter's hand-crafted barrier as a reference row), or, for a controller
without a policy (the nominal controller, alone and behind the ``dcbf`` filter), every learned CBF of the robot and
the reference. Controllers: ``policy`` (the checkpoint's policy alone), ``policy:cbf``, ``policy:prior``,
``policy:dcbf`` (behind each run-time filter, :mod:`egcbf.control.filters`), ``nominal`` and ``nominal:dcbf``.

The default plan (:class:`CertifyConfig`): the quadrotor's EGCBF+ and GCBF+ of every shipped training seed, at
N = 64 (l = 2) and N = 512 (l = 4) (the training density, 8 agents per m^3), with 0 and 8 obstacles; each robot of
the GCBF+ benchmark suite (its GCBF+ and EGCBF+), policy alone and nominal, at N = 64 and 256 in that suite's arenas
(docs/gcbfplus.md), and the planar unicycle at N = 64 and 128 in its own (l = 16), with 0 and 8 obstacles.
Evaluation seed 0 (Table I's); never a training or validation seed.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..io.report import code_version, machine_info
from ..robots import DEFAULT_ROBOT

__all__ = ["CONTROLLERS", "Cell", "CertifyConfig", "Learned", "run_cell"]

#: controller names of a cell (module doc)
CONTROLLERS = ("policy", "policy:cbf", "policy:prior", "policy:dcbf", "nominal", "nominal:dcbf")
#: the hand-crafted reference barrier's name
REFERENCE = "dcbf"
#: (N, arena side l) of the other robots: the GCBF+ suite's in that suite's arenas (docs/gcbfplus.md), the planar
#: unicycle's in its own (docs/robots.md)
SUITE_SIZES = {
    "double_integrator": ((64, 11.3), (256, 16.0)),
    "single_integrator": ((64, 11.3), (256, 22.6)),
    "dubins_car": ((64, 11.3), (256, 22.6)),
    "linear_drone": ((64, 4.0), (256, 6.35)),
    "unicycle": ((64, 16.0), (128, 16.0)),
}


@dataclass(frozen=True)
class Learned:
    """A shipped learned checkpoint: its ``label`` (``<algo>-s<training seed>``), robot and directory (relative
    to the checkpoints root)."""

    label: str
    robot: str
    path: str

    @property
    def barrier(self) -> str:
        """The name of its CBF's rows in the report."""
        return self.label if self.robot == DEFAULT_ROBOT else f"{self.robot}/{self.label}"


@dataclass(frozen=True)
class Cell:
    """One recorded rollout set (module doc): ``controller`` on ``robot`` with the policy of ``learned`` (``None``
    for ``nominal`` controllers), scored against ``barriers`` (names: :attr:`Learned.barrier` or ``"dcbf"``)."""

    robot: str
    controller: str
    learned: Learned | None
    num_agents: int
    area: float
    obstacles: int
    episodes: int
    barriers: tuple[str, ...]

    @property
    def run(self) -> str:
        return self.learned.label if self.learned is not None else "hand-crafted"

    @property
    def filename(self) -> str:
        """Its file under the results folder."""
        return (
            f"{self.robot}/{self.run}/{self.controller.replace(':', '-')}_N{self.num_agents}_obs{self.obstacles}.json"
        )

    @property
    def name(self) -> str:
        return f"{self.robot} {self.run} {self.controller} N {self.num_agents} obstacles {self.obstacles}"


@dataclass(frozen=True)
class CertifyConfig:
    """What ``egcbf certify`` measures (module doc). ``window``: the look-ahead ``W`` (steps) of the miss, false-safe
    and conservativeness rates; ``stride``: the thinning of the sampled states (:mod:`~egcbf.certify.rates`)."""

    seed: int = 0
    window: int = 32
    stride: int = 4
    checkpoints: Path = Path("checkpoints")
    out: Path = Path("docs/results/certificate")
    quadrotor_sizes: tuple[tuple[int, float, int], ...] = ((64, 2.0, 8), (512, 4.0, 2))
    suite_episodes: tuple[int, ...] = (8, 2)
    obstacles: tuple[int, ...] = (0, 8)
    quadrotor_seeds: tuple[int, ...] = (0, 1, 2)
    suite: tuple[str, ...] = tuple(SUITE_SIZES)
    workers: int = 2
    device: str = "cpu"
    only: str | None = None  # keep the cells whose name contains this

    def __post_init__(self):
        if self.window < 1 or self.stride < 1 or self.workers < 1:
            raise ValueError("window, stride and workers must be >= 1")
        bad = [r for r in self.suite if r not in SUITE_SIZES]
        if bad:
            raise ValueError(f"unknown suite robots {bad}; choose from {list(SUITE_SIZES)}")

    def learned(self) -> list[Learned]:
        """Every checkpoint whose CBF is certified."""
        out = []
        for algo in ("egcbf+", "gcbf+"):
            for s in self.quadrotor_seeds:
                out.append(Learned(f"{algo}-s{s}", DEFAULT_ROBOT, algo if s == 0 else f"seeds/{algo}-s{s}"))
        for robot in self.suite:
            out += [Learned(f"{algo}-s0", robot, f"{robot}/{algo}") for algo in ("gcbf+", "egcbf+")]
        return out

    def cells(self) -> list[Cell]:
        """Every cell of the plan, largest ``N`` first (``only`` applied)."""
        learned = self.learned()
        cells = []
        for robot in (DEFAULT_ROBOT, *self.suite):
            mine = [c for c in learned if c.robot == robot]
            if robot == DEFAULT_ROBOT:
                sizes = self.quadrotor_sizes
                policy_ctrls, nominal_ctrls = CONTROLLERS[:4], CONTROLLERS[4:]
                ref = (REFERENCE,)
            else:
                sizes = tuple((n, l, e) for (n, l), e in zip(SUITE_SIZES[robot], self.suite_episodes))
                policy_ctrls, nominal_ctrls, ref = ("policy",), ("nominal",), ()
            for n, area, episodes in sizes:
                for k in self.obstacles:
                    for ck in mine:
                        for ctrl in policy_ctrls:
                            cells.append(Cell(robot, ctrl, ck, n, area, k, episodes, (ck.barrier, *ref)))
                    for ctrl in nominal_ctrls:
                        cells.append(Cell(robot, ctrl, None, n, area, k, episodes,
                                          (*(c.barrier for c in mine), *ref)))  # fmt: skip
        if self.only:
            cells = [c for c in cells if self.only in c.name]
        return sorted(cells, key=lambda c: (-c.num_agents, c.robot != DEFAULT_ROBOT))

    def key(self, cell: Cell, shas: dict[str, str]) -> dict:
        """What a stored cell's counts depend on: the settings and the SHA-256 of every checkpoint involved."""
        return {
            "robot": cell.robot, "controller": cell.controller, "run": cell.run, "num_agents": cell.num_agents,
            "area": cell.area, "obstacles": cell.obstacles, "episodes": cell.episodes, "seed": self.seed,
            "window": self.window, "stride": self.stride, "barriers": list(cell.barriers),
            "checkpoints": {k: shas[k] for k in sorted(shas)},
        }  # fmt: skip


@dataclass(frozen=True)
class CellTask:
    """What a worker needs to run one cell (picklable)."""

    cell: Cell
    config: CertifyConfig
    paths: dict[str, str] = field(default_factory=dict)  # barrier name -> checkpoint directory
    threads: int = 1


def _controller(task: CellTask, dev):
    from ..control.resolve import POLICY, resolve

    cell = task.cell
    method, _, kind = cell.controller.partition(":")
    if method == "nominal":
        return resolve(cell.controller, robot=cell.robot).controller
    return resolve(f"{POLICY}:{kind}" if kind else POLICY, task.paths[cell.learned.barrier], device=dev).controller


def _barriers(task: CellTask, dev) -> dict:
    from ..control.filters import DCBF_FILTER_BARRIER
    from ..train.checkpoint import load_network
    from .barriers import BrakingBarrier, LearnedBarrier

    out = {}
    for name in task.cell.barriers:
        if name == REFERENCE:
            out[name] = BrakingBarrier(DCBF_FILTER_BARRIER)
        else:
            cbf, train_cfg = load_network(task.paths[name], "cbf", dev)
            out[name] = LearnedBarrier(cbf, train_cfg.alpha)
    return out


def run_cell(task: CellTask) -> dict:
    """Roll the cell's episodes out and count every barrier's rates: the cell file's content but its key."""
    from ..env import EnvConfig
    from ..evaluate.episodes import episode_seed
    from .rates import count_rates, pool_counts
    from .rollout import roll_out

    saved = torch.get_num_threads()
    torch.set_num_threads(task.threads)
    try:
        t0 = time.perf_counter()
        cell, cfg = task.cell, task.config
        dev = torch.device(cfg.device)
        env = EnvConfig.for_robot(cell.robot, num_agents=cell.num_agents, area_size=cell.area,
                                  num_obstacles=cell.obstacles)  # fmt: skip
        controller = _controller(task, dev)
        barriers = _barriers(task, dev)
        seeds = [episode_seed(cfg.seed, cell.num_agents, e) for e in range(cell.episodes)]
        counts = {name: [] for name in barriers}
        ever = []
        for s in seeds:  # one episode at a time: memory stays that of one episode's record
            traj = roll_out(controller, barriers, env, [s], device=dev)
            for name, b in barriers.items():
                counts[name].append(count_rates(traj, name, b.kappa, window=cfg.window, stride=cfg.stride))
            ever.append(traj.collision.any(0).double().mean().item())
        return {
            "barriers": {k: pool_counts(v) for k, v in counts.items()},
            "safe_rate": 1.0 - sum(ever) / len(ever),
            "wall_s": round(time.perf_counter() - t0, 2),
            "machine": machine_info(),
            "code": code_version(),
        }
    finally:
        torch.set_num_threads(saved)


def with_paths(cell: Cell, cfg: CertifyConfig) -> CellTask:
    """The task of ``cell``: every checkpoint it reads, resolved under ``cfg.checkpoints``."""
    by_name = {c.barrier: c for c in cfg.learned()}
    paths = {n: str(cfg.checkpoints / by_name[n].path) for n in cell.barriers if n in by_name}
    if cell.learned is not None:
        paths[cell.learned.barrier] = str(cfg.checkpoints / cell.learned.path)
    return CellTask(cell, dataclasses.replace(cfg), paths)
