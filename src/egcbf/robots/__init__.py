"""Robots of the swarm as plug-ins (:class:`Robot`): the quadrotor of the paper, a planar unicycle, and GCBF+'s
single and double integrators, linear drone and Dubins car.

``make_robot("unicycle")`` builds one by name; :func:`register_robot` adds a user's robot to the registry the
environment (``EnvConfig.robot``), the learner and the CLI (``--robot``) read. See docs/robots.md.
"""

from __future__ import annotations

import functools

from .base import Robot, rk4_step
from .dubins import DubinsCar, DubinsParams
from .integrators import DoubleIntegrator, IntegratorParams, LinearDrone, SingleIntegrator
from .quadrotor import Quadrotor
from .unicycle import Unicycle, UnicycleParams

__all__ = [
    "BUILTIN_ROBOTS",
    "DEFAULT_ROBOT",
    "ROBOTS",
    "DoubleIntegrator",
    "DubinsCar",
    "DubinsParams",
    "IntegratorParams",
    "LinearDrone",
    "Quadrotor",
    "Robot",
    "SingleIntegrator",
    "Unicycle",
    "UnicycleParams",
    "make_robot",
    "register_robot",
    "rk4_step",
]

#: robot name -> class (the class is called with its ``params``, or with none for the defaults)
ROBOTS: dict[str, type[Robot]] = {
    "quadrotor": Quadrotor,
    "unicycle": Unicycle,
    "single_integrator": SingleIntegrator,
    "double_integrator": DoubleIntegrator,
    "linear_drone": LinearDrone,
    "dubins_car": DubinsCar,
}


#: the robot of the paper, and of every setting that names none (``EnvConfig.robot``, ``--robot``)
DEFAULT_ROBOT = "quadrotor"
#: the robots shipped with egcbf: never replaced by a registration
BUILTIN_ROBOTS = frozenset(ROBOTS)


def register_robot(cls: type[Robot] | None = None, *, replace: bool = False):
    """Add a :class:`Robot` subclass to :data:`ROBOTS` under its ``name`` (usable as a class decorator, bare or as
    ``@register_robot(replace=True)``). A name already taken by another class is refused unless ``replace``; the
    built-in robots' names are always refused (name yours differently). The same class defined again (its module
    imported or run anew) replaces its earlier self."""
    if cls is None:
        return functools.partial(register_robot, replace=replace)
    if not (isinstance(cls, type) and issubclass(cls, Robot)) or not isinstance(cls.name, str) or not cls.name:
        raise TypeError(f"register_robot needs a Robot subclass with a name, got {cls!r}")
    taken = ROBOTS.get(cls.name)
    reloaded = taken is not None and (taken.__module__, taken.__qualname__) == (cls.__module__, cls.__qualname__)
    if taken is not None and taken is not cls and not reloaded:  # a module run again re-registers its own class
        if cls.name in BUILTIN_ROBOTS:
            raise ValueError(
                f"cannot register {cls.__qualname__} as {cls.name!r}: that is a built-in robot's name "
                f"({taken.__qualname__}); give your robot another name"
            )
        if not replace:
            raise ValueError(
                f"a robot named {cls.name!r} is already registered ({taken.__module__}.{taken.__qualname__}); "
                "rename yours, or pass replace=True to replace it"
            )
    ROBOTS[cls.name] = cls
    _shared.cache_clear()
    return cls


def make_robot(name: str, params=None) -> Robot:
    """The robot called ``name`` with ``params`` (``None``: its defaults). Robots are immutable: equal
    ``(name, params)`` (hashable params, e.g. frozen dataclasses) share one instance, so that the networks,
    the environment and the learner can ask for the robot on every step at no cost."""
    try:
        hash(params)
    except TypeError:
        return _build(name, params)
    return _shared(name, params)


def _build(name: str, params) -> Robot:
    try:
        cls = ROBOTS[name]
    except KeyError:
        raise ValueError(f"unknown robot {name!r}; choose one of {sorted(ROBOTS)}") from None
    return cls() if params is None else cls(params)


@functools.lru_cache(maxsize=64)
def _shared(name: str, params) -> Robot:
    return _build(name, params)
