"""What the equivariance study (docs/equivariance.md) trains and evaluates: its arms, their runs and their cells.

An *arm* is one training recipe run for several methods and training seeds under one wall-time budget, and what it
is evaluated on. The arms test the paper's three claims:

* ``paper-cpu`` and ``paper-cpu-mlp``: the paper's training regime (8 agents, ``l = 2``, 5 obstacles) with our heads
  and with the paper's MLP heads; zero-shot evaluation at ``l = 4`` for N = 8 ... 512 and at fixed density past it
  (claim 1, generalization), and their validation curves (claim 2, convergence);
* ``low-data``: ``paper-cpu`` with a quarter of the rollouts per update (claim 2, sample efficiency);
* ``crossing``: ``paper-cpu`` trained on scenes with a preferred direction (starts in ``x < l/2``, goals in
  ``x > l/2``), evaluated on those scenes rotated by 0, 90 and 180 degrees and on the uniform ones (claim 3);
* ``cpu-20``, ``no-closest``, ``mlp-cbf``, ``mlp-policy``: the ``cpu`` recipe for 20 minutes, then with each of its
  three departures from the paper switched off in turn (closest-approach edge features, soft-min CBF head, edge-sum
  policy head), to test whether they are what closes the gap between the groups.

Layout under ``ROOT`` (``docs/results/equivariance``): ``checkpoints/<arm>/<algo>`` (training seed 0) and
``checkpoints/<arm>/seeds/<algo>-s<k>`` (the layout of ``egcbf reproduce --checkpoints``), each the run's ``best/``
and its ``metrics.csv``; ``cells/<arm>/`` the ``egcbf reproduce`` cells of the arm; ``rotated/<algo>-s<k>/`` the
rotated-world evaluations (``<scene>-yaw<deg>-N<n>.json``: the metrics row with its per-episode values).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..algo.config import TrainConfig

__all__ = [
    "ARMS",
    "EVAL_SEED",
    "ROOT",
    "Arm",
    "RotatedCell",
    "Run",
    "arm",
    "rotated_cells",
    "scale_area",
]

ROOT = Path("docs/results/equivariance")
#: the evaluation seed of every cell of the study (episodes ``episode_seed(EVAL_SEED, N, e)``); training uses seeds
#: 0-2 and validates on ``seed + 1000``
EVAL_SEED = 0


@dataclass(frozen=True)
class Run:
    """One training run: ``algo`` with training seed ``seed`` under its arm's recipe."""

    arm: str
    algo: str
    seed: int

    @property
    def name(self) -> str:
        return f"{self.algo}-s{self.seed}"

    def checkpoint_dir(self, root: str | Path = ROOT) -> Path:
        """Where the run's selected checkpoint is kept: ``checkpoints/<arm>/<algo>`` for seed 0, else
        ``checkpoints/<arm>/seeds/<algo>-s<k>``."""
        base = Path(root) / "checkpoints" / self.arm
        return base / self.algo if self.seed == 0 else base / "seeds" / self.name


@dataclass(frozen=True)
class Arm:
    """A training recipe (``preset`` with ``overrides`` of :class:`egcbf.algo.config.TrainConfig` fields, ``minutes`` of
    the training process's CPU time per run, one torch thread: ``max_cpu_minutes``, a budget the other jobs on the
    machine do not eat into, with the preset's wall-time limit lifted), the ``(algo, seed)`` runs made with it, and
    its evaluation: ``table`` (Table I's sizes at ``l = 4`` with ``episodes`` each, and ``scale_sizes`` at the
    density of N = 512) or ``rotated``."""

    name: str
    preset: str
    runs: tuple[tuple[str, int], ...]
    minutes: float
    claim: str
    evaluation: str = "table"
    overrides: dict[str, Any] = field(default_factory=dict)
    episodes: int = 20
    table_sizes: tuple[int, ...] = (8, 16, 64, 128, 256, 512)
    scale_sizes: tuple[int, ...] = ()
    scale_agent_episodes: int = 20 * 512

    def config(self, algo: str, seed: int) -> TrainConfig:
        """The run's full training config."""
        return TrainConfig.preset(
            algo, self.preset, seed=seed, max_wall_minutes=None, max_cpu_minutes=float(self.minutes), **self.overrides
        )

    def all_runs(self) -> list[Run]:
        return [Run(self.name, a, s) for a, s in self.runs]

    def algos(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(a for a, _ in self.runs))

    def seeds(self, algo: str) -> tuple[int, ...]:
        return tuple(s for a, s in self.runs if a == algo)


#: CPU minutes per run of the paper-regime arms (8 agents; about 3 s an update on the 2-core CI machine's cores)
PAPER_MINUTES = 8.0
PM = PAPER_MINUTES
_PLUS3 = (("egcbf+", 0), ("gcbf+", 0), ("egcbf+", 1), ("gcbf+", 1), ("egcbf+", 2), ("gcbf+", 2))
_PAIRS0 = (("egcbf+", 0), ("gcbf+", 0))

ARMS: tuple[Arm, ...] = (
    Arm("paper-cpu", "paper-cpu", (*_PLUS3, ("egcbf", 0), ("gcbf", 0)), PM, "generalization, convergence",
        scale_sizes=(1024, 2048, 4096)),
    Arm("paper-cpu-mlp", "paper-cpu-mlp", (*_PLUS3, ("egcbf", 0), ("gcbf", 0)), PM, "generalization, convergence"),
    Arm("crossing", "paper-cpu", (*_PAIRS0, ("egcbf+", 1), ("gcbf+", 1)), PM, "transfer to transformed states",
        evaluation="rotated", overrides={"scene": "crossing"}),
    Arm("low-data", "paper-cpu", (*_PAIRS0, ("egcbf", 0), ("gcbf", 0)), PM, "sample efficiency",
        overrides={"rollout_envs": 1}),
    Arm("cpu-20", "cpu", _PAIRS0, 20, "heads ablation (the cpu recipe, 20 minutes)"),
    Arm("no-closest", "cpu", _PAIRS0, 20, "heads ablation", overrides={"model": {"edge_closest_approach": False}}),
    Arm("mlp-cbf", "cpu", _PAIRS0, 20, "heads ablation", overrides={"model": {"cbf_head": "mlp"}}),
    Arm("mlp-policy", "cpu", _PAIRS0, 20, "heads ablation", overrides={"model": {"policy_head": "mlp"}}),
)  # fmt: skip


def arm(name: str) -> Arm:
    """The arm called ``name`` (a ``ValueError`` naming the arms otherwise)."""
    for a in ARMS:
        if a.name == name:
            return a
    raise ValueError(f"unknown arm {name!r}; choose from {[a.name for a in ARMS]}")


@dataclass(frozen=True)
class RotatedCell:
    """One rotated-world evaluation of a ``crossing`` run: ``scene`` rotated by ``yaw`` degrees, ``num_agents`` in
    an arena of side ``area`` with ``obstacles`` obstacles, ``episodes`` episodes."""

    scene: str
    yaw: float
    num_agents: int
    area: float
    obstacles: int
    episodes: int = 50

    def path(self, run: Run, root: str | Path = ROOT) -> Path:
        return Path(root) / "rotated" / run.name / f"{self.scene}-yaw{self.yaw:g}-N{self.num_agents}.json"


def rotated_cells() -> list[RotatedCell]:
    """The training distribution (8 agents, ``l = 2``, 5 obstacles) and a larger swarm (64 agents, ``l = 4``), each
    as trained (yaw 0), rotated by 90 and 180 degrees, and uniform (the unbiased distribution)."""
    out = []
    for n, area, obstacles in ((8, 2.0, 5), (64, 4.0, 0)):
        out += [RotatedCell("crossing", yaw, n, area, obstacles) for yaw in (0.0, 90.0, 180.0)]
        out.append(RotatedCell("uniform", 0.0, n, area, obstacles))
    return out


def scale_area(num_agents: int, reference: int = 512, area: float = 4.0) -> float:
    """The side of the arena holding ``num_agents`` at the density of ``reference`` agents at ``area`` (as
    ``egcbf reproduce``)."""
    return round(area * (num_agents / reference) ** (1.0 / 3.0), 4)
