"""What ``egcbf robustness`` evaluates: fault axes, their levels, the controllers, and one ``egcbf reproduce`` sweep
per level (docs/robustness.md).

Each :class:`Axis` is one kind of fault (:mod:`egcbf.faults`) at five levels from none to severe; the ``field`` axis
holds the perfect world and the default field conditions (:data:`egcbf.faults.DEFAULT_FIELD`). Every level is a
:class:`egcbf.reproduce.SweepConfig` with that fault spec (its cells live under ``OUT/faults/<spec>/``; level 0 is the
perfect world, shared by every axis): the same cells, keys, resumption and backends (processes, Ray) as
``egcbf reproduce``.

A controller that does not read the agents' messages (:func:`reads_sensing`: the centralized QP, the nominal
controller) is evaluated on a level's state-level faults only (:func:`state_level`), and not at all on an axis made
of message and LiDAR faults alone; the report says so.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..faults import DEFAULT_FIELD, parse_faults
from ..reproduce import SweepConfig
from ..reproduce.paper import base_method, method_filter

__all__ = ["AXES", "Axis", "RobustnessConfig", "axis", "reads_sensing", "state_level"]


@dataclass(frozen=True)
class Axis:
    """One fault axis: ``levels`` (numbers in ``unit``, the first 0) and ``spec(level)``, the fault spec of a level."""

    name: str
    title: str
    unit: str
    levels: tuple[float, ...]
    spec: Callable[[float], str]

    def specs(self) -> list[str]:
        """The canonical spec of each level (``"none"`` for level 0)."""
        return [parse_faults(self.spec(x)).spec() if x else "none" for x in self.levels]


AXES: tuple[Axis, ...] = (
    Axis("field", "default field conditions", "0: none, 1: default", (0, 1), lambda x: "default"),
    Axis("sensing", "state-estimate noise", "position std, m (velocity std: twice, m/s)",
         (0, 0.005, 0.01, 0.03, 0.1), lambda x: f"pos={x:g},vel={2 * x:g}"),
    Axis("loss", "message loss", "probability", (0, 0.1, 0.3, 0.5, 0.8), lambda x: f"loss={x:g}"),
    Axis("delay", "message delay", "control steps", (0, 1, 2, 4, 8), lambda x: f"delay={int(x)}"),
    Axis("thrust", "thrust gain error", "+- fraction", (0, 0.05, 0.1, 0.2, 0.3), lambda x: f"thrust_gain={x:g}"),
    Axis("act_delay", "actuation delay", "control steps", (0, 1, 2, 3, 4), lambda x: f"act_delay={int(x)}"),
    Axis("wind", "wind (x) with gusts of half its strength", "m/s^2", (0, 0.5, 1, 2, 4),
         lambda x: f"wind={x:g}/0/0,gust={x / 2:g}"),
    Axis("noncoop", "non-cooperative agents hovering", "fraction", (0, 0.02, 0.05, 0.1, 0.2),
         lambda x: f"noncoop={x:g}"),
    Axis("noncoop_straight", "non-cooperative agents flying straight", "fraction", (0, 0.02, 0.05, 0.1, 0.2),
         lambda x: f"noncoop={x:g},noncoop_mode=straight"),
    Axis("lidar", "LiDAR range noise (drop rate: twice)", "range std, m", (0, 0.01, 0.03, 0.1, 0.3),
         lambda x: f"lidar={x:g},lidar_drop={min(0.9, 2 * x):g}"),
)  # fmt: skip

assert parse_faults(AXES[0].spec(1)) == DEFAULT_FIELD


def axis(name: str) -> Axis:
    """The axis called ``name`` (a ``ValueError`` naming the axes otherwise)."""
    for a in AXES:
        if a.name == name:
            return a
    raise ValueError(f"unknown fault axis {name!r}; choose from {[a.name for a in AXES]}")


def reads_sensing(method: str) -> bool:
    """Whether ``method``'s controller perceives message and LiDAR faults (``reads_sensing`` on the controller: the
    learned policies alone, which build their graph from what the agents perceive, and the QPs and filters that read
    their neighbours from the messages)."""
    from ..control.controllers import CONTROLLERS

    if method_filter(method) != "none":
        from ..algo.filtered import FilteredController

        return bool(getattr(FilteredController, "reads_sensing", False))
    base = base_method(method)
    if base in CONTROLLERS:
        return bool(getattr(CONTROLLERS[base], "reads_sensing", False))
    return True  # a learned policy alone (egcbf.algo.learner.LearnedController)


def state_level(spec: str) -> str:
    """``spec`` without its message and LiDAR faults (what a controller that does not read messages perceives)."""
    f = parse_faults(spec)
    return dataclasses.replace(f, msg_loss=0.0, msg_delay=0, lidar_noise=0.0, lidar_drop=0.0).spec()


@dataclass(frozen=True)
class RobustnessConfig:
    """The robustness sweep: ``controllers`` (``egcbf reproduce`` method names) at ``num_agents`` in ``[0, area]^3``
    without obstacles and with ``obstacles``, ``episodes`` per cell on evaluation ``seed``, for every level of
    ``axes``; learned checkpoints from ``checkpoints`` (training seed 0), cells in ``out``; ``max_steps`` the episode
    length (``None``: the environment's)."""

    controllers: tuple[str, ...] = ("nominal", "ccbf", "dcbf", "gcbf+", "egcbf+", "egcbf+:dcbf")
    axes: tuple[str, ...] = tuple(a.name for a in AXES)
    num_agents: tuple[int, ...] = (128, 512)
    area: float = 4.0
    obstacles: int = 8
    episodes: int = 20
    seed: int = 0
    max_steps: int | None = None
    checkpoints: Path = Path("checkpoints")
    out: Path = Path("docs/results/robustness")
    workers: int = 2
    backend: str = "process"
    device: str = "cpu"

    def __post_init__(self) -> None:
        for name in self.axes:
            axis(name)
        if not self.controllers:
            raise ValueError("controllers is empty")

    def sweeps(self) -> list[tuple[str, str, SweepConfig]]:
        """``(axis, spec, sweep)`` for every level of every axis, the perfect world once, first; a controller that
        does not read messages runs a level's state-level part, or nothing where that is the perfect world."""
        out, seen = [], set()
        for a in (axis(n) for n in self.axes):
            for spec in a.specs():
                for spec_run, methods in self._groups(spec):
                    if (spec_run, methods) in seen or not methods:
                        continue
                    seen.add((spec_run, methods))
                    out.append((a.name, spec_run, self.sweep(spec_run, methods)))
        out.sort(key=lambda t: t[1] != "none")  # the perfect world first: every level is compared with it
        return out

    def _groups(self, spec: str) -> list[tuple[str, tuple[str, ...]]]:
        readers = tuple(m for m in self.controllers if reads_sensing(m))
        others = tuple(m for m in self.controllers if not reads_sensing(m))
        reduced = state_level(spec)
        if spec == "none" or reduced == spec:
            return [(spec, self.controllers)]
        groups = [(spec, readers)]
        if reduced != "none":
            groups.append((reduced, others))
        return groups

    def sweep(self, spec: str, methods: tuple[str, ...]) -> SweepConfig:
        """The ``egcbf reproduce`` sweep of ``methods`` under ``spec``."""
        return SweepConfig(
            methods=methods,
            num_agents=self.num_agents,
            area=self.area,
            obstacles=self.obstacles,
            obstacle_methods=methods,
            episodes=self.episodes,
            train_seeds=(0,),
            seed_methods=(),
            scale_sizes=(),
            scale_methods=(),
            seed=self.seed,
            max_steps=self.max_steps,
            checkpoints=self.checkpoints,
            out=self.out,
            baselines=None,
            device=self.device,
            workers=self.workers,
            backend=self.backend,
            faults=spec,
        )

    def cell_spec(self, method: str, spec: str) -> str | None:
        """The spec ``method`` actually runs at a level ``spec`` (``None``: not evaluated there)."""
        if spec == "none" or reads_sensing(method):
            return spec
        reduced = state_level(spec)
        return None if reduced == "none" else reduced
