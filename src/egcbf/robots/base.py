"""The robot interface: everything the swarm, the graph, the learner and the evaluation need to know about a robot.

A robot is a plug-in. It declares

* its **dynamics** in control-affine form, ``x' = f0(x) + f1(x) u``, and an integrator ``step`` for one control
  period with the control held (zero-order hold), with the actuator box ``clip_control``;
* its **symmetry**: a ``groupcanon`` group and how it acts on states and controls (``state_type``,
  ``control_type``: groupcanon FieldTypes, so the property tests can check every claim);
* its **geometry** in the world: ``dim`` (2 or 3), ``positions(x)``, ``velocities(x)`` (world frame), a unit
  ``heading(x)`` (the direction of the LiDAR pattern and of the frames), ``frames(x)`` (one group element per
  agent: canonicalization puts every agent's neighbourhood in its own frame), the state of an agent at rest
  (``rest_state``);
* its **graph features**: ``node_fields`` (the agent node's features after the kind one-hot, as groupcanon feature
  types; must contain ``"v"``, the world velocity) and ``agent_features(x)``;
* its **controllers**: ``nominal_control(x, goals)`` (equivariant), and ``interfaces``: the names of the command
  interfaces the learned methods may act on (built by :func:`egcbf.algo.interface.make_interface`; ``"control"``,
  the normalized raw control, works for every robot), with ``command_feature(name)``, how the group acts on it;
* the **defaults** of an environment for it (``env_defaults``: arena, radii, LiDAR, time step).

:mod:`egcbf.robots.quadrotor` (the paper's rigid body), the planar cars (:mod:`egcbf.robots.unicycle`, the
Dubins car) and the point masses (:mod:`egcbf.robots.integrators`: single and double integrator, linear drone)
implement it (``egcbf.robots.BUILTIN_ROBOTS``); ``examples/new_robot.py`` and docs/robots.md show how to add one.
Shapes: ``x`` ``(*batch, state_dim)``, ``u`` ``(*batch, control_dim)``, points and vectors ``(*batch, dim)``.
"""

from __future__ import annotations

import functools
import math
from typing import Any, ClassVar

import torch
from torch import Tensor

from groupcanon import FeatureType, FieldType, Group
from groupcanon.features import Scalar
from groupcanon.groups import Trivial

__all__ = ["Robot", "hold_at_limit", "require_positive", "rk4_step"]


def require_positive(params, names) -> None:
    """Raise ``ValueError`` naming the first of ``params``' fields ``names`` that is not a finite number ``> 0``
    (the check of every robot's parameter dataclass)."""
    for name in names:
        v = getattr(params, name)
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
            raise ValueError(f"{type(params).__name__}.{name} must be a finite number > 0, got {v!r}")


def _not_implemented(robot, method: str) -> NotImplementedError:
    """The error of a :class:`Robot` plug-in that lacks ``method``, naming the class and the method."""
    return NotImplementedError(
        f"{type(robot).__name__} does not implement Robot.{method}(), which a robot plug-in must define "
        "(docs/robots.md lists what each method returns)"
    )


class Robot:
    """Base class of robots (module doc). Subclasses set the class attributes and implement the methods."""

    #: the registry name (``--robot``)
    name: ClassVar[str] = ""
    #: spatial dimension of positions, obstacles and LiDAR (2 or 3)
    dim: ClassVar[int] = 3
    state_dim: ClassVar[int] = 0
    control_dim: ClassVar[int] = 0
    #: the config name of the symmetry group (:data:`egcbf.nn.models.GROUPS`)
    group_name: ClassVar[str] = ""
    #: command interfaces the learned methods may use; the first is the default
    interfaces: ClassVar[tuple[str, ...]] = ()
    #: agents closer than this to their goals are frozen (parked by the environment's step, :meth:`parked`; GCBF+'s
    #: Dubins car: 0.5 r); 0: never
    goal_freeze_radius: float = 0.0
    #: whether the LiDAR rays are fixed in the world frame (``heading`` then is a constant, not a vector of the
    #: group; the ray pattern must be invariant under the group's rotations instead)
    world_fixed_lidar: ClassVar[bool] = False
    #: :class:`egcbf.env.EnvConfig` defaults for this robot (fields not named keep the EnvConfig defaults)
    env_defaults: ClassVar[dict[str, Any]] = {}
    #: the GCBF+ reference's training labels for this robot where they differ from the defaults (EnvConfig's
    #: ``unsafe_*`` fields; ``EnvConfig.for_robot(name, **robot.reference_labels)``)
    reference_labels: ClassVar[dict[str, Any]] = {}
    #: where the state holds the world position and the world velocity (:meth:`perturbed`); ``None``: not a slice
    #: of the state (a robot without one overrides :meth:`perturbed`)
    position_index: ClassVar[slice | None] = None
    velocity_index: ClassVar[slice | None] = None
    #: the control is the velocity (relative degree 1 in position: the single integrator); the per-edge QPs and the
    #: second-order barriers need a robot whose velocity is part of its state
    kinematic: ClassVar[bool] = False
    #: named groups of control channels (:mod:`egcbf.faults`: a per-agent gain error on ``"thrust"``, a gain and a
    #: bias on ``"torque"``); a robot without them only takes the faults' ``gain`` on every channel
    actuator_groups: ClassVar[dict[str, tuple[int, ...]]] = {}
    #: whether the run-time safety filters (:mod:`egcbf.control.filters`: per-agent QPs over a world acceleration
    #: command, the attitude loop tracking it) apply to this robot's learned policies
    run_time_filters: ClassVar[bool] = False
    #: whether the robot's decentralized CBF-QP can read its obstacle rows from each agent's own LiDAR hits instead
    #: of the obstacle map (``egcbf eval --obstacle-sensing lidar``)
    lidar_obstacle_rows: ClassVar[bool] = False
    #: whether the robot can fly a world acceleration command as a full-state setpoint through a firmware-like
    #: tracker (:meth:`fly_setpoint`; ``egcbf eval --low-level setpoint``)
    flies_setpoints: ClassVar[bool] = False
    #: whether the graph's mirror in a horizontal plane is defined (``SwarmGraph.reflect_z``: a 3-D robot whose
    #: node features are a velocity, a body-to-world rotation and body rates)
    mirror_z: ClassVar[bool] = False
    #: which training recipes of :mod:`egcbf.algo.presets` the robot takes: ``"paper"`` (the paper's quadrotor
    #: recipes) or ``"planar"`` (the recipe of GCBF+'s benchmark robots and of any new robot)
    training_recipe: ClassVar[str] = "planar"

    #: the robot's parameters (a frozen dataclass; ``None`` if it has none)
    params: Any = None
    #: the symmetry group (set by the subclass, as an attribute or a property)
    group: Group
    #: how the group acts on a state
    state_type: FieldType
    #: how the group acts on a control
    control_type: FieldType

    # ------------------------------------------------------------------------------------------- dynamics
    def f0(self, x: Tensor) -> Tensor:
        """Drift ``(*batch, state_dim)``."""
        raise _not_implemented(self, "f0")

    def f1(self, x: Tensor) -> Tensor:
        """Input matrix ``(*batch, state_dim, control_dim)``."""
        raise _not_implemented(self, "f1")

    def xdot(self, x: Tensor, u: Tensor) -> Tensor:
        """``f0(x) + f1(x) u`` ``(*batch, state_dim)``."""
        return self.f0(x) + (self.f1(x) @ u[..., None])[..., 0]

    def step(self, x: Tensor, u: Tensor, dt: float, substeps: int = 1, integrator: str = "rk4") -> Tensor:
        """The state after ``dt`` with ``u`` held (no clipping here: :meth:`clip_control` first)."""
        raise _not_implemented(self, "step")

    def fly_setpoint(
        self, x: Tensor, accel: Tensor, dt: float, integrator: str = "rk4", clip: bool = True
    ) -> tuple[Tensor, Tensor]:
        """One control period ``dt`` (s) of ``x`` ``(*batch, S)`` flying the world acceleration command ``accel``
        ``(*batch, d)`` (m/s^2) as a full-state setpoint (position and velocity held at their values now) through
        the robot's firmware-like tracker: the next states and the mean control over the period. Only for a robot
        with :attr:`flies_setpoints`."""
        raise ValueError(f"the {self.name} has no setpoint tracker (flies_setpoints is False): evaluate it with its "
                         "own low level")  # fmt: skip

    def control_bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """``lo, hi`` ``(control_dim,)``: the actuator box (dtype and device of ``like``)."""
        raise _not_implemented(self, "control_bounds")

    def effective_control_bounds(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """``lo, hi`` ``(*batch, control_dim)``: the part of the actuator box that acts at state ``x``.

        A robot whose step clips part of its state (a speed limit) discards any control that pushes a component
        already at its limit further out; a QP or a policy that counted on such a control would expect a motion
        that never happens (a double integrator at its speed limit "braking" by pushing less hard forward). Those
        robots narrow the box there, to the control that holds the component at its limit
        (:func:`hold_at_limit`). Default: the box."""
        lo, hi = self.control_bounds(x)
        shape = (*x.shape[:-1], self.control_dim)
        return lo.expand(shape), hi.expand(shape)

    def clip_control(self, u: Tensor) -> Tensor:
        """``u`` clamped into the actuator box."""
        lo, hi = self.control_bounds(u)
        return torch.maximum(torch.minimum(u, hi), lo)

    def check_state(self, x: Tensor, atol: float = 1e-3) -> None:
        """Raise ``ValueError`` naming the first bad agent if a state is not finite or off its manifold."""
        if x.shape[-1] != self.state_dim:
            raise ValueError(f"{self.name} states must be (..., {self.state_dim}), got {tuple(x.shape)}")
        if not bool(torch.isfinite(x).all()):
            bad = (~torch.isfinite(x)).any(-1).nonzero()[0].tolist()
            raise ValueError(f"state x holds NaN or inf (first at index {tuple(bad)})")

    # ------------------------------------------------------------------------------------------- geometry
    def positions(self, x: Tensor) -> Tensor:
        raise _not_implemented(self, "positions")

    def velocities(self, x: Tensor) -> Tensor:
        """World-frame velocities ``(*batch, dim)``."""
        raise _not_implemented(self, "velocities")

    def perturbed(self, x: Tensor, dp: Tensor, dv: Tensor | None = None) -> Tensor:
        """The state ``x`` with its world position moved by ``dp`` and its world velocity changed by ``dv``
        ``(*batch, dim)`` (as far as the state holds a velocity: a kinematic robot keeps none, a car keeps the
        component along its heading). Sensing noise and external pushes (:mod:`egcbf.faults`) use it."""
        if self.position_index is None:
            raise _not_implemented(self, "perturbed")
        out = x.clone()
        out[..., self.position_index] += dp.to(x.dtype)
        if dv is not None and self.velocity_index is not None:
            out[..., self.velocity_index] += dv.to(x.dtype)
        return out

    def heading(self, x: Tensor) -> Tensor:
        """Unit heading ``(*batch, dim)`` (horizontal for 3-D robots): the LiDAR pattern turns with it."""
        raise _not_implemented(self, "heading")

    def motion_direction(self, x: Tensor) -> Tensor:
        """The direction the agent moves in ``(*batch, dim)``, for the approach labels
        (``EnvConfig.unsafe_approach_*``): ``v / (|v| + 1e-4)`` (GCBF+'s double integrator), so about zero at rest.
        An equivariant vector (it turns with the agent's state)."""
        v = self.velocities(x)
        return v / (torch.linalg.vector_norm(v, dim=-1, keepdim=True) + 1e-4)

    def frames(self, x: Tensor) -> Tensor:
        """The agents' frames ``(*batch, *group.element_shape)``: ``frames(phi_g x) = g frames(x)``. A robot of a
        finite-rotation group may instead give each agent a set of ``F`` frames, ``(*batch, F, *element_shape)``,
        with ``frames(phi_g x) = g frames(x)`` as sets; the networks then average over them."""
        raise _not_implemented(self, "frames")

    def rest_state(self, positions: Tensor, yaw: Tensor) -> Tensor:
        """Agents at rest at ``positions`` ``(*batch, dim)`` with heading angle ``yaw`` ``(*batch,)``."""
        raise _not_implemented(self, "rest_state")

    # ------------------------------------------------------------------------------------------- features
    @property
    def node_fields(self) -> dict[str, FeatureType]:
        """The agent node's features after the kind one-hot (goals and LiDAR hits hold zeros there)."""
        raise _not_implemented(self, "node_fields")

    def node_type(self, group: Group) -> FieldType:
        """The node features ``kind (3) | node_fields`` declared over ``group`` (the robot's, or the trivial one)."""
        return FieldType(group, {"kind": Scalar(3), **self.node_fields})

    @functools.cached_property
    def node_layout(self) -> FieldType:
        """The node features' channel layout (over the trivial group): slice a field by name,
        ``robot.node_layout.slice("v")``, instead of indexing channels by hand."""
        return self.node_type(Trivial())

    def agent_features(self, x: Tensor) -> Tensor:
        """``(*batch, sum of node_fields dims)``: the agent node's features after the kind one-hot."""
        raise _not_implemented(self, "agent_features")

    # ------------------------------------------------------------------------------------------- control
    def nominal_control(self, x: Tensor, goals: Tensor) -> Tensor:
        """The equivariant nominal controller's control ``(*batch, control_dim)`` towards ``goals``
        ``(*batch, dim)``, clipped to the actuator box unless the robot documents otherwise (the Dubins car's law
        is the reference's, unclipped: the environment clips every command before it acts)."""
        raise _not_implemented(self, "nominal_control")

    def attitudes(self, x: Tensor) -> Tensor:
        """``(*batch, 3, 3)`` body-to-world rotations of states ``x`` ``(*batch, S)``; ``AttributeError`` for a robot
        without an attitude matrix."""
        raise AttributeError(f"a {self.name} has no attitude matrix")

    def cbf_qps(self) -> dict[str, type]:
        """The robot's hand-crafted CBF-QP baselines by controller name (``{"ccbf": ..., "dcbf": ...}``): classes
        whose instances are controllers ``u, info = ctrl(state, env_config)`` (:mod:`egcbf.control.controllers`),
        built with their keyword arguments. ``{}``: none (the robot still has its nominal and brisk laws)."""
        return {}

    def parked(self, x: Tensor) -> Tensor:
        """The state ``(*batch, S)`` an agent frozen at its goal holds (:attr:`goal_freeze_radius`): ``x`` at rest,
        its velocity zeroed. Robots that freeze their agents must define it."""
        raise _not_implemented(self, "parked")

    def brisk_control(self, x: Tensor, goals: Tensor) -> Tensor:
        """A goal-seeking law ``(*batch, control_dim)`` that cruises at the robot's speed limits: the base law a
        learned policy may act around instead of :meth:`nominal_control` (``ModelConfig.base_law = "brisk"``),
        for benchmarks timed by a horizon. Equivariant like the nominal law. Default: the nominal law (a robot
        whose nominal controller already cruises at its limits)."""
        return self.nominal_control(x, goals)

    @property
    def rejects_disturbances(self) -> bool:
        """Whether this robot implements the optional :meth:`reject_disturbance`."""
        return type(self).reject_disturbance is not Robot.reject_disturbance

    def reject_disturbance(self, x: Tensor, u: Tensor, accel: Tensor) -> Tensor:
        """The command ``(*batch, control_dim)`` that, under a world-frame disturbance acceleration ``accel``
        ``(*batch, dim)`` (wind force over mass, an actuator's gain error), does what ``u`` does without it (as far
        as the actuators can), clipped to the actuator box (``accel == 0``: ``u`` itself, for a ``u`` in the box).
        Equivariant: ``accel`` is a world vector. Optional: the agents' disturbance observer (``egcbf.faults``,
        ``dist_obs``) needs it."""
        raise NotImplementedError(
            f"{type(self).__name__} has no disturbance rejection (Robot.reject_disturbance, optional: the agents' "
            "disturbance observer, egcbf.faults dist_obs, needs it)"
        )

    def command_feature(self, interface: str) -> FeatureType:
        """How the group acts on the normalized command of ``interface`` (one of :attr:`interfaces`): the policy's
        output type (a ``Vector`` for a world-frame command, a ``Scalar`` for an invariant one)."""
        raise _not_implemented(self, "command_feature")

    def check_interface(self, name: str) -> None:
        """Raise ``ValueError`` unless ``name`` is one of this robot's command :attr:`interfaces`."""
        if name not in self.interfaces:
            raise ValueError(f"the {self.name} has the command interfaces {self.interfaces}, not {name!r}")

    # ------------------------------------------------------------------------------------------- identity
    def __repr__(self) -> str:
        return f"{type(self).__name__}()"

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and self.params == getattr(other, "params", None)

    def __hash__(self) -> int:
        return hash((type(self).__name__, self.params))


def rk4_step(xdot, x: Tensor, u: Tensor, dt: float, substeps: int = 1, project=None) -> Tensor:
    """``substeps`` classical Runge-Kutta 4 steps of ``x' = xdot(x, u)`` over ``dt`` with ``u`` held; ``project``
    (a function of the state, or ``None``) maps each sub-step's result back onto the state manifold."""
    if int(substeps) != substeps or substeps < 1:
        raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
    h = dt / int(substeps)
    for _ in range(int(substeps)):
        k1 = xdot(x, u)
        k2 = xdot(x + 0.5 * h * k1, u)
        k3 = xdot(x + 0.5 * h * k2, u)
        k4 = xdot(x + h * k3, u)
        x = x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
        if project is not None:
            x = project(x)
    return x


def hold_at_limit(
    lo: Tensor, hi: Tensor, value: Tensor, limit: float, hold: Tensor, tol: float = 1e-6
) -> tuple[Tensor, Tensor]:
    """The box ``lo, hi`` ``(..., k)`` narrowed where a clipped state component is at its limit: channel ``k``
    drives component ``value[..., k]`` (clipped to ``+-limit`` after each step) and ``hold[..., k]`` is the control
    that keeps it constant; at ``+limit`` controls above ``hold`` are discarded by the clip, at ``-limit`` those
    below (:meth:`Robot.effective_control_bounds`). ``hold`` is kept inside the box."""
    hold = torch.minimum(torch.maximum(hold, lo), hi)
    hi = torch.where(value >= limit - tol, torch.minimum(hi, hold), hi)
    lo = torch.where(value <= -limit + tol, torch.maximum(lo, hold), lo)
    return lo, hi
