"""Hand-crafted controllers with one call signature, for evaluation: ``u, info = controller(state, env_config)``.

``state`` is an :class:`egcbf.env.SwarmState` (``B`` environments of ``N`` agents), ``env_config`` its
:class:`egcbf.env.EnvConfig`; ``u`` ``(B, N, control_dim)`` (the quadrotor: body-frame ``(tau, F3)``) in ``state.x``'s
dtype and device, clipped to the actuators; ``info`` a dict with at least ``qp_ms`` (wall time of the controller's
optimization, 0 for the nominal controller), ``num_slack`` and ``num_failed`` (QPs that needed slack / fell back; 0
for the nominal one).

Every robot has its nominal law (``"nominal"``) and its brisk law (``"brisk"``); its CBF-QP baselines are the ones
it declares (``Robot.cbf_qps``: the quadrotor's ``"ccbf"`` and ``"dcbf"``, the point masses' and cars'
acceleration-level ones). A controller with a learned part, or behind a run-time filter, is built by
:func:`egcbf.control.resolve.resolve`::

    ctrl = make_controller("ccbf")                          # the quadrotor's centralized CBF-QP
    ctrl = make_controller("dcbf", robot="double_integrator")
    u, info = ctrl(state, env.config)
"""

from __future__ import annotations

import time

from torch import Tensor

from ..robots import DEFAULT_ROBOT, ROBOTS, make_robot

__all__ = ["CONTROLLERS", "GENERIC_CONTROLLERS", "BriskController", "NominalController", "make_controller",
           "robot_controllers"]  # fmt: skip


def _info(t0: float) -> dict:
    return {"qp_ms": 0.0, "num_slack": 0, "num_failed": 0, "ctrl_ms": 1e3 * (time.perf_counter() - t0)}


class NominalController:
    """The robot's equivariant nominal controller (``Robot.nominal_control``), no safety."""

    name = "nominal"

    def __call__(self, state, env_config) -> tuple[Tensor, dict]:
        t0 = time.perf_counter()
        u = env_config.make_robot().nominal_control(state.x, state.goals)
        return u, _info(t0)


class BriskController:
    """A robot's brisk law (``Robot.brisk_control``: its nominal law retuned to cruise at its speed limits; the
    nominal law itself for a robot without one, the quadrotor included), no safety: the base law of a policy trained
    with ``ModelConfig.base_law = "brisk"``."""

    name = "brisk"

    def __call__(self, state, env_config) -> tuple[Tensor, dict]:
        t0 = time.perf_counter()
        u = env_config.make_robot().brisk_control(state.x, state.goals)
        return u, _info(t0)


#: the controllers of every robot
GENERIC_CONTROLLERS = {"nominal": NominalController, "brisk": BriskController}


def robot_controllers(robot: str = DEFAULT_ROBOT) -> dict[str, type]:
    """Controller name -> class of ``robot``'s hand-crafted controllers: :data:`GENERIC_CONTROLLERS` and the CBF-QPs
    the robot declares (``Robot.cbf_qps``). Raises ``ValueError`` for a robot not registered."""
    if robot not in ROBOTS:
        raise ValueError(f"unknown robot {robot!r}; choose one of {sorted(ROBOTS)}")
    return {**GENERIC_CONTROLLERS, **make_robot(robot).cbf_qps()}


#: the default robot's hand-crafted controllers, name -> class (``egcbf eval --controller``)
CONTROLLERS = robot_controllers()


def make_controller(name: str, robot: str = DEFAULT_ROBOT, **kwargs):
    """The hand-crafted controller ``name`` of ``robot`` (:func:`robot_controllers`), built with ``kwargs``: for
    the quadrotor's CBF-QPs a ``config=CBFQPConfig(...)`` and/or overrides of its fields or of
    :class:`egcbf.robots.quadrotor.barriers.BarrierConfig`'s (e.g. ``make_controller("ccbf", kind="hocbf",
    solver="proxsuite")``). Raises ``ValueError`` naming the robot's controllers for an unknown ``name``."""
    available = robot_controllers(robot)
    if name not in available:
        raise ValueError(f"unknown controller {name!r} for the {robot}; choose one of {sorted(available)}")
    return available[name](**kwargs)
