"""The fixed choices of the command line's options, as ``str`` enums: typer lists them in ``--help`` and refuses any
other value before the command runs, as one ``Error:`` line naming the flag and the choices
(:func:`choice_error`).

Each enum mirrors a registry of the library (``tests/egcbf/test_cli.py`` checks that they agree); the commands pass
the plain string (``.value``) on, so configs and results hold strings, never enum members. ``--device`` stays a
string (``cuda:1`` is as valid as ``cuda``: :func:`egcbf.cli.checks.parse_device` checks it), as do the comma lists
(``--compare``, ``--methods``), which are parsed and checked by their commands.
"""

from __future__ import annotations

import re
from enum import Enum

__all__ = [
    "ROBOT_METAVAR",
    "Backend",
    "Controller",
    "DemoMethod",
    "Dtype",
    "ExportFormat",
    "LearnedMethod",
    "Preset",
    "RobotName",
    "SafetyFilter",
    "SceneName",
    "choice_error",
    "robot_choice",
]


class Controller(str, Enum):
    """A hand-crafted controller (``egcbf.control.controllers.CONTROLLERS``): ``egcbf eval --controller``."""

    nominal = "nominal"
    brisk = "brisk"
    ccbf = "ccbf"
    dcbf = "dcbf"


class SafetyFilter(str, Enum):
    """A run-time safety filter of a learned policy (``egcbf.control.filters.FILTERS``): ``egcbf eval --filter``."""

    none = "none"
    cbf = "cbf"
    prior = "prior"
    dcbf = "dcbf"


class SceneName(str, Enum):
    """A scene layout (``egcbf.env.scenes.SCENES``): ``egcbf eval --scene``."""

    uniform = "uniform"
    crossing = "crossing"


class LearnedMethod(str, Enum):
    """A learned method (``egcbf.algo.config.LEARNED_METHODS``): ``egcbf train --algo``."""

    gcbf = "gcbf"
    gcbf_plus = "gcbf+"
    egcbf = "egcbf"
    egcbf_plus = "egcbf+"


class DemoMethod(str, Enum):
    """A learned method (its checkpoint in ``--checkpoints``) or a hand-crafted controller: ``egcbf demo --method``."""

    gcbf = "gcbf"
    gcbf_plus = "gcbf+"
    egcbf = "egcbf"
    egcbf_plus = "egcbf+"
    nominal = "nominal"
    brisk = "brisk"
    ccbf = "ccbf"
    dcbf = "dcbf"


class Preset(str, Enum):
    """A training preset (``egcbf.algo.config.PRESETS``): ``egcbf train --preset``."""

    cpu = "cpu"
    paper_cpu = "paper-cpu"
    paper_cpu_mlp = "paper-cpu-mlp"
    cpu_torque = "cpu-torque"
    paper = "paper"
    tiny = "tiny"
    gcbfplus = "gcbfplus"


class RobotName(str, Enum):
    """The robots shipped (``egcbf.robots.BUILTIN_ROBOTS``): what ``--help`` lists for ``--robot``. The option itself
    takes any robot registered when the command runs (:func:`robot_choice`), a user's own too."""

    quadrotor = "quadrotor"
    unicycle = "unicycle"
    single_integrator = "single_integrator"
    double_integrator = "double_integrator"
    linear_drone = "linear_drone"
    dubins_car = "dubins_car"


class Dtype(str, Enum):
    """The floating-point type of an evaluation (``egcbf.cli.eval.DTYPES``): ``egcbf eval --dtype``."""

    float32 = "float32"
    float64 = "float64"


class ExportFormat(str, Enum):
    """The file format of an exported agent controller (``egcbf.deploy.export.FORMATS``): ``egcbf export --format``."""

    torchscript = "torchscript"
    onnx = "onnx"


class Backend(str, Enum):
    """Where the reproduction's cells run (``egcbf.reproduce.plan.BACKENDS``): ``egcbf reproduce --backend``."""

    process = "process"
    ray = "ray"


# typer's (and click's) message for a value outside the choices: "'ppo' is not one of 'gcbf', 'gcbf+'."
_NOT_ONE_OF = re.compile(r"""(?P<value>'[^']*'|"[^"]*") is not one of (?P<choices>.+?)\.?$""", re.DOTALL)


def robot_choice(value: str | None) -> str | None:
    """The ``--robot`` option's check: a name in ``egcbf.robots.ROBOTS`` as it stands when the command runs (the
    shipped robots and any registered with :func:`egcbf.robots.register_robot`), else typer's one-line choice error
    (:func:`choice_error`)."""
    import typer

    from ..robots import ROBOTS

    if value is None or value in ROBOTS:
        return value
    raise typer.BadParameter(f"{value!r} is not one of {', '.join(repr(name) for name in ROBOTS)}.")


#: the ``--robot`` option's metavar: the shipped robots (any registered one is accepted too)
ROBOT_METAVAR = "[" + "|".join(m.value for m in RobotName) + "|a registered robot]"


def choice_error(flag: str, name: str, message: str) -> str | None:
    """The one-line message for a value of option ``flag`` (parameter ``name``) outside its choices, from typer's
    ``message``: ``"--algo: unknown algo 'ppo'; choose one of gcbf, gcbf+, egcbf, egcbf+"``; ``None`` if
    ``message`` is not about choices."""
    found = _NOT_ONE_OF.search(message.strip())
    if found is None:
        return None
    choices = [a or b for a, b in re.findall(r"'([^']*)'|\"([^\"]*)\"", found["choices"])]
    listed = ", ".join(choices) if choices else found["choices"]
    return f"{flag}: unknown {name.replace('_', ' ')} {found['value']}; choose one of {listed}"
