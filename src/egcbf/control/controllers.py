"""Controllers with one call signature, for evaluation: ``u, info = controller(state, env_config)``.

``state`` is an :class:`egcbf.env.SwarmState` (``B`` environments of ``N`` agents), ``env_config`` its
:class:`egcbf.env.EnvConfig`; ``u`` ``(B, N, 4)`` body-frame ``(tau, F3)`` in ``state.x``'s dtype and device, clipped
to the actuators; ``info`` a dict with at least ``qp_ms`` (wall time of the controller's optimization, 0 for the
nominal controller), ``num_slack`` and ``num_failed`` (QPs that needed slack / fell back; 0 for the nominal one).

    ctrl = make_controller("ccbf")            # "nominal", "brisk", "ccbf", "dcbf"
    u, info = ctrl(state, env.config)
"""

from __future__ import annotations

import time

from torch import Tensor

from ..robots.quadrotor.cbf_qp import CBFQPConfig, CentralizedCBFQP
from ..robots.quadrotor.dcbf_qp import DecentralizedCBFQP
from ..robots.quadrotor.nominal import DEFAULT_GAINS, DEFAULT_MAX_POSITION_ERROR, NominalGains, nominal_control

__all__ = [
    "CONTROLLERS",
    "BriskController",
    "CBFQPConfig",
    "CentralizedCBFQP",
    "DecentralizedCBFQP",
    "NominalController",
    "make_controller",
]


class NominalController:
    """The equivariant nominal controller, no safety: the quadrotor's geometric controller
    (:func:`~.quadrotor.nominal.nominal_control`, with ``gains`` and ``max_position_error``), or another robot's
    own ``Robot.nominal_control``."""

    name = "nominal"

    def __init__(self, gains: NominalGains = DEFAULT_GAINS, max_position_error: float = DEFAULT_MAX_POSITION_ERROR):
        self.gains = gains
        self.max_position_error = max_position_error

    def __call__(self, state, env_config) -> tuple[Tensor, dict]:
        t0 = time.perf_counter()
        if env_config.robot == "quadrotor":
            u = nominal_control(state.x, state.goals, env_config.params, self.gains, self.max_position_error)
        else:
            u = env_config.make_robot().nominal_control(state.x, state.goals)
        info = {"qp_ms": 0.0, "num_slack": 0, "num_failed": 0, "ctrl_ms": 1e3 * (time.perf_counter() - t0)}
        return u, info


class BriskController:
    """A robot's brisk law (``Robot.brisk_control``: its nominal law retuned to cruise at its speed limits; the
    nominal law itself for a robot without one, the quadrotor included), no safety: the base law of a policy trained
    with ``ModelConfig.base_law = "brisk"``."""

    name = "brisk"

    def __call__(self, state, env_config) -> tuple[Tensor, dict]:
        t0 = time.perf_counter()
        u = env_config.make_robot().brisk_control(state.x, state.goals)
        info = {"qp_ms": 0.0, "num_slack": 0, "num_failed": 0, "ctrl_ms": 1e3 * (time.perf_counter() - t0)}
        return u, info


CONTROLLERS = {
    "nominal": NominalController,
    "brisk": BriskController,
    "ccbf": CentralizedCBFQP,
    "dcbf": DecentralizedCBFQP,
}
#: robots whose "dcbf" is the control-affine dCBF-QP (:mod:`egcbf.control.point_mass_qp`): GCBF+'s point masses and
#: its cars
POINT_MASSES = ("single_integrator", "double_integrator", "linear_drone", "dubins_car", "unicycle")


def make_controller(name: str, robot: str = "quadrotor", **kwargs):
    """Controller by name: ``"nominal"``, ``"brisk"`` (:class:`BriskController`), ``"ccbf"`` (centralized
    CBF-QP), ``"dcbf"`` (decentralized CBF-QP), for ``robot`` (the quadrotor's QPs; for GCBF+'s point masses and
    cars ``"dcbf"`` is :class:`egcbf.control.point_mass_qp.PointMassDCBF` and ``"ccbf"`` its centralized
    :class:`~egcbf.control.point_mass_qp.PointMassCCBF`).

    Keyword arguments go to the constructor: for the CBF-QPs a ``config=CBFQPConfig(...)`` and/or overrides of its
    fields or of :class:`egcbf.robots.quadrotor.barriers.BarrierConfig`'s (e.g. ``make_controller("ccbf", kind="hocbf",
    solver="proxsuite")``); for the nominal controller ``gains`` and ``max_position_error``.
    """
    if name in ("ccbf", "dcbf") and robot in POINT_MASSES:
        from .point_mass_qp import PointMassCCBF, PointMassDCBF

        return (PointMassCCBF if name == "ccbf" else PointMassDCBF)(**kwargs)
    if name in ("ccbf", "dcbf") and robot != "quadrotor":
        names = ", ".join(POINT_MASSES)
        raise ValueError(f"the hand-crafted CBF-QPs are written for the quadrotor and {names}; not a {robot}")
    try:
        cls = CONTROLLERS[name]
    except KeyError:
        raise ValueError(f"unknown controller {name!r}; choose one of {sorted(CONTROLLERS)}") from None
    return cls(**kwargs)
