"""Control interfaces of the learned methods: what the policy, the learned-CBF QP and the loss act on.

The plant is always the full rigid body driven by body torque and thrust. An interface says which *command* the
learning works with, how the symmetry acts on it, and how a command becomes the body control:

* :class:`AccelInterface` (``"accel"``, the default of the ``cpu`` preset): a desired world acceleration
  ``a = A c`` (``c`` normalized, ``A = accel_unit`` m/s^2; hover is ``a = 0``), tracked by the attitude loop of the
  equivariant geometric controller (:func:`~.quadrotor.nominal.track_acceleration`). The command is a world-frame
  vector (``Vector(3)``: ``c -> Rz c``); its bounds are a box in the agent's own yaw frame, so clipping commutes
  with the symmetry. This is where the hand-crafted CBF-QPs act, and what the GCBF+ reference's CrazyFlie does with
  velocity targets (its learned CBF never acts on raw torques).
* :class:`TorqueInterface` (``"torque"``): the body torque and thrust themselves, normalized by the actuator box
  (:mod:`egcbf.algo.actions`); invariant under the symmetry. Kept for comparison (docs/learning.md).
* :class:`ControlInterface` (``"control"``): any robot's raw control ``u = s c`` (``s`` the larger bound of each
  channel, so ``c`` lies in a box within ``[-1, 1]``), with ``Lf h``, ``Lg h`` from the robot's control-affine
  dynamics and the loss's next state from its integrator. The planar unicycle's interface; invariant controls
  (``robot.command_feature``).

Each interface gives, for normalized commands ``c`` ``(..., k)``:

* ``nominal(x, goals)``: the nominal controller's command; ``clip(x, c)``: ``c`` projected into the bounds that
  act at ``x`` (``state_bounds(x)``: the box, narrowed where a robot's speed clip would discard a push,
  :meth:`egcbf.robots.base.Robot.effective_control_bounds`);
* ``apply(x, c)``: the body control ``(tau, F3)`` in physical units (what the plant receives);
* ``to_local`` / ``from_local``: the coordinates in which the bounds are a box ``[lo, hi]`` (the agent's yaw
  frame for accelerations, the identity for torques), used by the QP;
* ``lie_derivatives(cbf, graph, x)``: ``h``, ``Lf h`` ``(B, N)`` and ``Lg h`` ``(B, N, N, k)`` over the commands
  of all agents, through the interface's *model* (below);
* ``model_step(x, c, env_config)``: the next state the loss's ``hdot`` term sees.

The model (``AccelInterface.model``) is how the CBF's derivative along a command is computed:

* ``"ideal"``: the translational double integrator the command defines, ``p' = v``, ``v' = A c`` (attitude and body
  rates held), as the hand-crafted CBF-QPs use: ``Lf h = sum_j dh/dp_j . v_j``, ``Lg_j h = A dh/dv_j``;
* ``"closed_loop"``: one control step of the true closed loop ``x' = step(x, track(x, A c))``, linearized in ``c``
  at the nominal command (as the GCBF+ reference does through its inner LQR): ``Lg_j h = dh(x')/dc_j / dt``. Over
  one 25 ms step the attitude loop realizes ~6 % of a sideways command and all of a vertical one, so this model
  sees ~18x more vertical than sideways authority (docs/learning.md compares the two).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..env import EnvConfig
from ..env.graph import SwarmGraph, refresh_graph
from ..robots import Quadrotor, Robot
from ..robots.quadrotor import dynamics as dyn
from ..robots.quadrotor.nominal import (
    DEFAULT_GAINS,
    NominalGains,
    desired_heading,
    nominal_acceleration,
    nominal_control,
    track_acceleration,
)
from .actions import control_bounds, control_scale, normalize, unnormalize
from .qp import CBFQPResult, cbf_jacobian, solve_cbf_qp

__all__ = [
    "INTERFACES",
    "AccelInterface",
    "CommandInterface",
    "ControlInterface",
    "TorqueInterface",
    "make_interface",
    "solve_command_qp",
]

INTERFACES = ("accel", "torque", "control")


class CommandInterface:
    """Base class (module doc). Subclasses set ``name`` and ``dim`` and implement the methods."""

    name: str = ""
    dim: int = 0

    def bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """``lo, hi`` ``(k,)``: the box of the local coordinates."""
        raise NotImplementedError

    def state_bounds(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """``lo, hi`` (``(k,)`` or ``(*batch, k)``): the box of the local coordinates that acts at the states ``x``
        (:meth:`egcbf.robots.base.Robot.effective_control_bounds`). Default: :meth:`bounds`."""
        return self.bounds(x)

    def to_local(self, x: Tensor, c: Tensor) -> Tensor:
        return c

    def from_local(self, x: Tensor, z: Tensor) -> Tensor:
        return z

    def clip(self, x: Tensor, c: Tensor) -> Tensor:
        """``c`` projected into the bounds that act at ``x`` (:meth:`state_bounds`; a clamp in local coordinates,
        its gradient 0 where active)."""
        lo, hi = (t.to(c) for t in self.state_bounds(x))
        return self.from_local(x, torch.maximum(torch.minimum(self.to_local(x, c), hi), lo))

    def nominal(self, x: Tensor, goals: Tensor) -> Tensor:
        raise NotImplementedError

    def apply(self, x: Tensor, c: Tensor) -> Tensor:
        raise NotImplementedError

    def acceleration(self, c: Tensor) -> Tensor | None:
        """The world acceleration ``(..., 3)`` (m/s^2) the commands ``c`` ask for, or ``None`` (default) where the
        command is not an acceleration (torques, a raw control): what a setpoint-flying low level tracks."""
        return None

    def lie_derivatives(
        self, cbf: nn.Module, graph: SwarmGraph, x: Tensor, env: EnvConfig | None = None, c_lin: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """``h``, ``Lf h`` ``(B, N)``, ``Lg h`` ``(B, N, N, k)`` over the world-frame commands of all agents.
        ``env`` (control period, integrator) and ``c_lin`` (the linearization point) are needed by models that
        step the closed loop only."""
        raise NotImplementedError

    def model_step(self, x: Tensor, c: Tensor, env: EnvConfig) -> Tensor:
        raise NotImplementedError


@dataclass
class TorqueInterface(CommandInterface):
    """Body torque and thrust normalized by the actuator box (``k = 4``, invariant under the symmetry)."""

    params: dyn.QuadrotorParams = dyn.DEFAULT_PARAMS
    name = "torque"
    dim = 4

    def bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        return control_bounds(like)

    def nominal(self, x: Tensor, goals: Tensor) -> Tensor:
        return normalize(nominal_control(x, goals, self.params), self.params)

    def apply(self, x: Tensor, c: Tensor) -> Tensor:
        return unnormalize(c, self.params)

    def lie_derivatives(
        self, cbf: nn.Module, graph: SwarmGraph, x: Tensor, env: EnvConfig | None = None, c_lin: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        h, jac = cbf_jacobian(cbf, graph, x)
        xd = x.detach()
        lf = torch.einsum("bijs,bjs->bi", jac, dyn.f0(xd, self.params))
        lg = torch.einsum("bijs,bjsk->bijk", jac, dyn.f1(xd, self.params)) * control_scale(self.params, h)
        return h, lf, lg

    def model_step(self, x: Tensor, c: Tensor, env: EnvConfig) -> Tensor:
        return dyn.step(x, self.apply(x, c), env.dt, self.params, env.substeps, env.integrator)


def _heading(x: Tensor) -> tuple[Tensor, Tensor]:
    """``cos, sin`` ``(..., 1)`` of each agent's yaw (its body x axis projected on the horizontal plane)."""
    h = desired_heading(x[..., dyn.ROT].reshape(*x.shape[:-1], 3, 3))
    return h[..., 0:1], h[..., 1:2]


@dataclass
class AccelInterface(CommandInterface):
    """A desired world acceleration ``a = accel_unit * c`` tracked by the attitude loop (module doc).

    Attributes:
        accel_unit: ``A`` (m/s^2), the unit of the normalized command (the QP's and the loss's metric).
        horizontal: bound (m/s^2) on each horizontal component in the agent's yaw frame.
        down, up: bounds (m/s^2) on the vertical acceleration, ``-down <= a_z <= up`` (hover is 0).
        model: ``"ideal"`` or ``"closed_loop"`` (module doc).
    """

    params: dyn.QuadrotorParams = dyn.DEFAULT_PARAMS
    gains: NominalGains = DEFAULT_GAINS
    accel_unit: float = 5.0
    horizontal: float = 7.0
    down: float = 4.9
    up: float = 7.0
    model: str = "ideal"
    name = "accel"
    dim = 3

    def __post_init__(self) -> None:
        for f in ("accel_unit", "horizontal", "down", "up"):
            if not getattr(self, f) > 0:
                raise ValueError(f"AccelInterface.{f} must be > 0, got {getattr(self, f)!r}")
        if self.model not in ("ideal", "closed_loop"):
            raise ValueError(f"AccelInterface.model must be 'ideal' or 'closed_loop', got {self.model!r}")

    def bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        kw = {"dtype": like.dtype, "device": like.device}
        a = self.accel_unit
        lo = torch.tensor((-self.horizontal / a, -self.horizontal / a, -self.down / a), **kw)
        hi = torch.tensor((self.horizontal / a, self.horizontal / a, self.up / a), **kw)
        return lo, hi

    def to_local(self, x: Tensor, c: Tensor) -> Tensor:
        cs, sn = _heading(x)
        cx, cy = c[..., 0:1], c[..., 1:2]
        return torch.cat((cs * cx + sn * cy, -sn * cx + cs * cy, c[..., 2:3]), -1)

    def from_local(self, x: Tensor, z: Tensor) -> Tensor:
        cs, sn = _heading(x)
        zx, zy = z[..., 0:1], z[..., 1:2]
        return torch.cat((cs * zx - sn * zy, sn * zx + cs * zy, z[..., 2:3]), -1)

    def nominal(self, x: Tensor, goals: Tensor) -> Tensor:
        return self.clip(x, nominal_acceleration(x, goals, self.gains) / self.accel_unit)

    def apply(self, x: Tensor, c: Tensor) -> Tensor:
        return track_acceleration(x, self.accel_unit * c, self.params, self.gains)

    def acceleration(self, c: Tensor) -> Tensor:
        return self.accel_unit * c

    def _ideal_step(self, x: Tensor, c: Tensor, dt: float) -> Tensor:
        a = self.accel_unit * c
        v = x[..., dyn.V]
        return torch.cat((x[..., dyn.P] + dt * v + 0.5 * dt * dt * a, x[..., 3:12], v + dt * a, x[..., dyn.W]), -1)

    def model_step(self, x: Tensor, c: Tensor, env: EnvConfig) -> Tensor:
        if self.model == "ideal":
            return self._ideal_step(x, c, env.dt)
        return dyn.step(x, self.apply(x, c), env.dt, self.params, env.substeps, env.integrator)

    def lie_derivatives(
        self, cbf: nn.Module, graph: SwarmGraph, x: Tensor, env: EnvConfig | None = None, c_lin: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """``h``, ``Lf h`` ``(B, N)``, ``Lg h`` ``(B, N, N, 3)`` over normalized world commands (module doc).

        ``"closed_loop"`` needs ``env`` (the control period and integrator) and linearizes at ``c_lin`` ``(B, N, 3)``
        (the nominal command, normally): ``Lf h + Lg h . c`` is then ``(h(x'(c)) - h(x)) / dt`` to first order.
        """
        if self.model == "ideal":
            h, jac = cbf_jacobian(cbf, graph, x)
            lf = torch.einsum("bijs,bjs->bi", jac[..., dyn.P], x.detach()[..., dyn.V].to(jac.dtype))
            return h, lf, self.accel_unit * jac[..., dyn.V]
        if env is None or c_lin is None:
            raise ValueError("the closed-loop model needs env and c_lin")
        xd, c0 = x.detach(), c_lin.detach().to(x.dtype)
        x_next = self.model_step(xd, c0, env)
        cols = []
        for k in range(3):  # d x'_j / d c_j: each agent's next state depends on its own command only
            e = torch.zeros_like(c0)
            e[..., k] = 1
            cols.append(torch.func.jvp(lambda c: self.model_step(xd, c, env), (c0,), (e,))[1])
        dxdc = torch.stack(cols, -1)  # (B, N, 18, 3)
        h0 = cbf(graph).detach().view(x.shape[:2])
        h1, jac = cbf_jacobian(cbf, refresh_graph(graph, x_next), x_next)
        lg = torch.einsum("bijs,bjsk->bijk", jac, dxdc) / env.dt
        lf = (h1 - h0) / env.dt - torch.einsum("bijk,bjk->bi", lg, c0)
        return h0, lf, lg


class ControlInterface(CommandInterface):
    """A robot's raw control, normalized: ``u = s c`` with ``s_k = max(|lo_k|, |hi_k|)`` of the actuator box
    (module doc). ``Lf h = sum_j dh/dx_j . f0(x_j)``, ``Lg_j h = dh/dx_j f1(x_j) s``; the next state is one control
    period of the robot's integrator."""

    name = "control"

    def __init__(self, robot: Robot):
        self.robot = robot
        self.dim = robot.control_dim

    def scale(self, like: Tensor) -> Tensor:
        """``s`` ``(k,)``: the larger bound of each channel, ``u = s c``."""
        lo, hi = self.robot.control_bounds(like)
        return torch.maximum(lo.abs(), hi.abs())

    def bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        lo, hi = self.robot.control_bounds(like)
        s = self.scale(like)
        return lo / s, hi / s

    def state_bounds(self, x: Tensor) -> tuple[Tensor, Tensor]:
        lo, hi = self.robot.effective_control_bounds(x)
        s = self.scale(x)
        return lo / s, hi / s

    def nominal(self, x: Tensor, goals: Tensor) -> Tensor:
        return self.robot.nominal_control(x, goals) / self.scale(x)

    def brisk(self, x: Tensor, goals: Tensor) -> Tensor:
        """The robot's :meth:`~egcbf.robots.base.Robot.brisk_control`, normalized."""
        return self.robot.brisk_control(x, goals) / self.scale(x)

    def apply(self, x: Tensor, c: Tensor) -> Tensor:
        return c * self.scale(c)

    def lie_derivatives(
        self, cbf: nn.Module, graph: SwarmGraph, x: Tensor, env: EnvConfig | None = None, c_lin: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        h, jac = cbf_jacobian(cbf, graph, x)
        xd = x.detach().to(jac.dtype)
        lf = torch.einsum("bijs,bjs->bi", jac, self.robot.f0(xd))
        lg = torch.einsum("bijs,bjsk->bijk", jac, self.robot.f1(xd)) * self.scale(jac)
        return h, lf, lg

    def model_step(self, x: Tensor, c: Tensor, env: EnvConfig) -> Tensor:
        return self.robot.step(x, self.apply(x, c), env.dt, env.substeps, env.integrator)


def make_interface(name: str, robot: Robot | dyn.QuadrotorParams | None = None, **kwargs) -> CommandInterface:
    """The interface called ``name`` for ``robot`` (default: the quadrotor; a ``QuadrotorParams`` means a quadrotor
    with those parameters): ``"accel"`` and ``"torque"`` (quadrotor; ``kwargs`` go to :class:`AccelInterface`) or
    ``"control"`` (any robot)."""
    if robot is None or isinstance(robot, dyn.QuadrotorParams):
        robot = Quadrotor(robot)
    if name not in robot.interfaces:
        raise ValueError(f"unknown control interface {name!r} for the {robot.name}; choose one of {robot.interfaces}")
    if name == "control":
        return ControlInterface(robot)
    if name == "accel":
        return AccelInterface(params=robot.params, **kwargs)
    return TorqueInterface(params=robot.params)


def solve_command_qp(
    itf: CommandInterface,
    cbf: nn.Module,
    graph: SwarmGraph,
    x: Tensor,
    c_nom: Tensor,
    env: EnvConfig,
    *,
    alpha: float,
    **solver,
) -> tuple[Tensor, CBFQPResult]:
    """The learned-CBF QP over the commands of ``itf`` (:mod:`egcbf.algo.qp`) for the states ``x`` ``(B, N, 18)``
    of ``graph``: ``Lg h`` by the interface's model, variables in the coordinates where the bounds are a box,
    reference ``c_nom`` ``(B, N, k)``. Returns the QP's commands in world coordinates (dtype of ``x``) and the
    solver's result. ``solver``: ``slack_linear``, ``slack_quadratic``, ``tol``, ``max_iter``, ``chunk``."""
    h, lf, lg = itf.lie_derivatives(cbf, graph, x, env, c_nom)
    lo, hi = itf.state_bounds(x)
    res = solve_cbf_qp(
        h, lf, itf.to_local(x[:, None].to(lg.dtype), lg), itf.to_local(x, c_nom), lo, hi, alpha=alpha, **solver
    )
    return itf.from_local(x.to(res.u.dtype), res.u).to(x.dtype), res
