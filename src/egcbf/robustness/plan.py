"""What ``egcbf robustness`` evaluates: fault axes, their levels, the controllers, and one ``egcbf reproduce`` sweep
per level (docs/robustness.md).

Each :class:`Axis` is one kind of fault (:mod:`egcbf.faults`) at five levels from none to severe; the ``field`` axis
holds the perfect world and the default field conditions (:data:`egcbf.faults.DEFAULT_FIELD`). Every level is a
:class:`egcbf.reproduce.SweepConfig` with that fault spec (its cells live under ``OUT/faults/<spec>/``; level 0 is the
perfect world, shared by every axis): the same cells, keys, resumption and backends (processes, Ray) as
``egcbf reproduce``.

A controller perceives the message and LiDAR faults only on the channels it reads (its ``reads_sensing``,
:func:`egcbf.faults.sensing.unread_faults`: the learned policies both, the dCBF-QP the messages, the centralized
QP and the nominal controller neither); each level runs the faults it perceives (:meth:`RobustnessConfig.cell_spec`),
and a level left with none of them (a LiDAR level for the dCBF-QP) is not run for it; the report says so.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..faults import DEFAULT_FIELD, parse_faults
from ..faults.sensing import unread_fields
from ..reproduce import SweepConfig

__all__ = ["AXES", "Axis", "RobustnessConfig", "axis", "perceived", "reads_sensing", "state_level"]


@dataclass(frozen=True)
class Axis:
    """One fault axis: ``levels`` (numbers in ``unit``, the first 0) and ``spec(level)``, the fault spec of a level.

    A fix's axis repeats the fault axis ``fixes`` (its levels) with the agents' handling added (:meth:`handling`);
    the report compares the two at level index ``compare`` (``None``: in the figures only).
    """

    name: str
    title: str
    unit: str
    levels: tuple[float, ...]
    spec: Callable[[float], str]
    fixes: str | None = None
    compare: int | None = None

    def specs(self) -> list[str]:
        """The canonical spec of each level (``"none"`` for level 0)."""
        return [parse_faults(self.spec(x)).spec() if x else "none" for x in self.levels]

    def handling(self) -> str:
        """The fields this fix's axis adds to the axis it repeats, as a spec (``""`` for a fault axis)."""
        if self.fixes is None:
            return ""
        x = self.levels[-1]
        mine, theirs = parse_faults(self.spec(x)).active(), parse_faults(axis(self.fixes).spec(x)).active()
        return ",".join(f"{k}={v}" for k, v in mine.items() if theirs.get(k) != v)

    def compared_level(self) -> float:
        """The level (in :attr:`unit`) at which the report compares this fix with the axis it repeats."""
        return self.levels[self.compare]

    def compared(self) -> tuple[str, str] | None:
        """``(spec without the fix, spec with it)`` at the level the report compares (``None``: none)."""
        if self.fixes is None or self.compare is None:
            return None
        return axis(self.fixes).specs()[self.compare], self.specs()[self.compare]


#: steps a receiver holds a lost neighbour's last message in the receivers' axes (0.125 s at dt = 0.025 s: a
#: neighbour closing at 1 m/s moves 12.5 cm meanwhile, which the prediction takes back up to its acceleration)
RECEIVER_HOLD = 5
RECEIVERS = f"hold={RECEIVER_HOLD},predict=1"

#: the default field conditions' faults shaped as a real swarm has them (the sweep's draws are white and
#: independent): an estimator's error wanders over about half a second, a crowded radio loses messages in runs of
#: 5 steps (125 ms) or more; the same levels
CORRELATED = "noise_tau=0.5,burst=5"

AXES: tuple[Axis, ...] = (
    Axis("field", "default field conditions", "0: none, 1: default", (0, 1), lambda x: "default"),
    Axis("field_correlated", "default field conditions, errors correlated in time and losses in bursts",
         "0: none, 1: default", (0, 1), lambda x: f"default,{CORRELATED}"),
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
    # the receivers' fix (docs/robustness.md, "Fixes"): the message axes again, every receiver holding a lost
    # neighbour's last message up to RECEIVER_HOLD steps and moving each message on at its velocity over its age
    Axis("field_receivers", "default field conditions, receivers holding and predicting", "0: none, 1: default",
         (0, 1), lambda x: f"default,{RECEIVERS}", fixes="field", compare=1),
    Axis("field_correlated_receivers", "default field conditions, correlated and bursty, receivers holding and "
         "predicting", "0: none, 1: default", (0, 1), lambda x: f"default,{CORRELATED},{RECEIVERS}",
         fixes="field_correlated", compare=1),
    Axis("loss_receivers", "message loss, receivers holding and predicting", "probability",
         (0, 0.1, 0.3, 0.5, 0.8), lambda x: f"loss={x:g},{RECEIVERS}", fixes="loss"),
    Axis("delay_receivers", "message delay, receivers predicting", "control steps", (0, 1, 2, 4, 8),
         lambda x: f"delay={int(x)},predict=1", fixes="delay"),
    # the agents' fix of actuation delay (docs/robustness.md, "Fixes"): each commands for its state predicted over
    # the delay through the robot's dynamics with its commands in flight (a Smith predictor)
    Axis("act_delay_predict", "actuation delay, agents predicting over it", "control steps", (0, 1, 2, 3, 4),
         lambda x: f"act_delay={int(x)},act_predict=1", fixes="act_delay", compare=2),
    # the agents' fix of wind and thrust errors (docs/robustness.md, "Fixes"): those axes again, every agent
    # estimating the acceleration acting on it beyond its model and cancelling it (a disturbance observer)
    Axis("wind_observer", "wind (x) with gusts, agents observing the disturbance", "m/s^2", (0, 0.5, 1, 2, 4),
         lambda x: f"wind={x:g}/0/0,gust={x / 2:g},dist_obs=1", fixes="wind", compare=2),
    Axis("thrust_observer", "thrust gain error, agents observing the disturbance", "+- fraction",
         (0, 0.05, 0.1, 0.2, 0.3), lambda x: f"thrust_gain={x:g},dist_obs=1", fixes="thrust", compare=4),
    # the agent-side fixes of the default field conditions at once (the receivers' and the disturbance observer; it
    # has no actuation delay to predict over): what a user would turn on
    Axis("field_fixes", "default field conditions, the receivers' fix and the disturbance observer",
         "0: none, 1: default", (0, 1), lambda x: f"default,{RECEIVERS},dist_obs=1", fixes="field", compare=1),
)  # fmt: skip

assert parse_faults(AXES[0].spec(1)) == DEFAULT_FIELD


def axis(name: str) -> Axis:
    """The axis called ``name`` (a ``ValueError`` naming the axes otherwise)."""
    for a in AXES:
        if a.name == name:
            return a
    raise ValueError(f"unknown fault axis {name!r}; choose from {[a.name for a in AXES]}")


def reads_sensing(method: str):
    """``method``'s controller's ``reads_sensing`` declaration (:func:`egcbf.control.resolve.reads_sensing`)."""
    from ..control.resolve import reads_sensing as declared

    return declared(method)


def perceived(method: str, spec: str) -> str:
    """``spec`` without the faults ``method``'s controller does not perceive (canonical spec)."""
    f = parse_faults(spec)
    return f.without(unread_fields(reads_sensing(method), f, method)).spec()


def state_level(spec: str) -> str:
    """``spec`` without its message and LiDAR faults (what a controller that reads no sensing perceives)."""
    f = parse_faults(spec)
    return f.without(unread_fields(False, f)).spec()


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
        """``(axis, spec, sweep)`` for every level of every axis, the perfect world once, first; each controller runs
        the part of a level it perceives (:meth:`cell_spec`), or nothing where that is the perfect world."""
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
        """The controllers of level ``spec`` grouped by the spec each runs (:meth:`cell_spec`), in order."""
        groups: dict[str, list[str]] = {}
        for m in self.controllers:
            run = self.cell_spec(m, spec)
            if run is not None:
                groups.setdefault(run, []).append(m)
        return [(s, tuple(ms)) for s, ms in groups.items()]

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
        """The spec ``method`` runs at level ``spec``: the faults it perceives (``None``: none of them, while the
        level has some; the level is then not run for it)."""
        if spec == "none":
            return spec
        run = perceived(method, spec)
        return None if run == "none" else run

    def unperceived(self, method: str, spec: str) -> tuple[str, ...]:
        """The fault fields of level ``spec`` that ``method`` does not perceive (absent from :meth:`cell_spec`)."""
        run = self.cell_spec(method, spec)
        seen = parse_faults(run).active() if run is not None else {}
        return tuple(k for k in parse_faults(spec).active() if k not in seen)
