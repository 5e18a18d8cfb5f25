"""Run-time safety filters around a learned policy: the policy proposes, a decentralized CBF-QP disposes.

Every agent ``i`` computes its policy's command ``a_pi,i`` (a world acceleration, the ``accel`` interface) from its
own graph neighbourhood, then solves one small QP over its own acceleration only::

    min  1/2 ||a_i - a_pi,i||^2 + 1/2 w2 s_i^2 + w1 s_i
    s.t. n_k . a_i + s_i >= b_k      (one row per neighbour and per LiDAR hit or obstacle it senses)
         the command box of the interface, in the agent's yaw frame;  s_i >= 0

and the attitude loop tracks the result. Nothing is exchanged between agents: each pair row is split in halves, each
agent enforcing its own half (the ``dCBF-QP``'s convention), so the two halves add up to the pair's condition when
both agents keep their halves. All ``B N`` QPs are one batch, solved (``cbf``, ``prior``) exactly by the batched dual
active-set method (:func:`egcbf.qp.dense_active_set.solve_dense_batch_active_set`, ``FilterConfig.qp_solver``'s
default) or by the interior-point solver of the dCBF-QP (:func:`egcbf.qp.dense_qp.solve_dense_batch_ipm`,
``qp_solver = "ipm"``); an agent whose QP fails (or whose solution fails the check) brakes. Three filters
(``FILTERS``), each a :class:`SafetyFilter` registered under its kind (``FILTER_CLASSES``:
:class:`EdgeBarrierFilter`, :class:`PriorBarrierFilter`, :class:`BrakingBarrierFilter`):

* ``"cbf"``: the checkpoint's **learned per-edge barriers**. The soft-min CBF head
  (:class:`egcbf.nn.edge_min.EdgeMinHead`) computes one barrier value ``b_ij(dp, dv; z_i)`` (m) per edge before
  its smooth minimum. With the ideal model of the command (``dp' = dv``, ``dv' = a_j - a_i``, the receiver's
  neighbourhood features ``z_i`` held fixed over the step, as the QP target holds the topology), the per-edge
  condition ``db_ij/dt + alpha (b_ij - margin) >= 0`` is linear in the accelerations:
  ``g_v . (a_j - a_i) >= -alpha (b_ij - margin) - g_p . dv`` with ``g_p, g_v`` the gradients of ``b_ij`` in
  ``dp, dv`` (one backward pass for all edges: each ``b_ij`` reads its own edge only). Agent rows take half of the
  right-hand side, LiDAR-hit rows (static points) all of it. Rows are normalized by ``|g_v|`` (units of m/s^2);
  rows with ``|g_v| < 1e-6`` s (pairs moving apart: no acceleration changes ``b`` within the step) are dropped.
* ``"prior"``: the same rows from the head's untrained prior ``b = d_min - D`` (closest-approach distance within
  the horizon minus the checkpoint's ``cbf_distance``): the ablation that shows what learning the barrier adds.
* ``"dcbf"`` (the recommended one): the hand-crafted pairwise and obstacle barriers of the dCBF-QP baseline (Wang
  et al.'s braking-distance barrier, :class:`~.dcbf_qp.DecentralizedCBFQP`) with the policy's command
  as the reference instead of the nominal one, its own settings (``DCBF_FILTER_BARRIER``), its QP box, and a
  look-ahead (``DCBF_FILTER_LOOKAHEAD``): the rows read every agent ``T`` seconds ahead under the acceleration it
  realized over the last step (under message faults a neighbour's as its message carries it), a predictor for the
  attitude loop's lag. Learned liveness, hand-crafted safety.

``FilteredController(None, None, config)`` filters the nominal controller's command instead (``dcbf``, ``prior``):
the ablation that shows what the policy adds. docs/safety_filters.md has the measurements behind every default.

Under faults (:mod:`egcbf.faults`) the policy and the ``cbf`` / ``prior`` rows read the agent's graph, which carries
the messages and the LiDAR scan as the agent receives them; the ``dcbf`` rows read the same messages
(:class:`~.dcbf_qp.DecentralizedCBFQP`) and the obstacle map, or with ``FilterConfig.obstacle_sensing = "lidar"``
the agent's own scan, every hit a point obstacle (the sensing of the learned controllers). ``reads_sensing`` says
what the whole controller perceives (:func:`filter_reads_sensing`): every channel with a policy (its graph) and for
``cbf`` and ``prior``; the messages (and with LiDAR-only sensing the LiDAR) for the ``dcbf`` filter of the nominal
command (``READS_SENSING``).

Every piece is an invariant or an equivariant of the agent's frame (edge vectors rotate with the scene, the box
turns with the agent, the policy is equivariant for EGCBF+), so the filtered controller of EGCBF+ stays SE2xR
equivariant (tested), and every input of agent ``i``'s QP lies within its sensing radius (tested). One difference
from the per-agent filter a robot runs (:class:`egcbf.deploy.agent.AgentFilteredController`): without message faults the
``dcbf`` rows take the neighbours within range at the look-ahead positions, so a neighbour closing from up to
``T`` times the closing speed beyond the radius (a few cm) counts, where a robot keeps only the ones it heard (as
the filter does under message faults); docs/safety_filters.md ("Cost") measures both rules.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor

from ..algo.config import TrainConfig
from ..algo.edge_qp import BRAKE_GAIN, SLACK_TOL, EdgeRows, edge_qp_commands, edge_rows
from ..algo.interface import make_interface
from ..algo.learner import policy_command
from ..env import EnvConfig, SwarmState
from ..env.graph import build_graph
from ..nn.models import CBFNet, ModelConfig, PolicyNet
from ..qp.sparse_qp import SlackPenalty
from ..robots.quadrotor.barriers import BarrierConfig
from ..robots.quadrotor.cbf_qp import OBSTACLE_SENSING, check_lidar_hits
from ..robots.quadrotor.dcbf_qp import DecentralizedCBFQP
from .names import FILTERS

__all__ = [
    "FILTERS",
    "FILTER_CLASSES",
    "QP_SOLVERS",
    "READS_SENSING",
    "BrakingBarrierFilter",
    "EdgeBarrierFilter",
    "EdgeRows",
    "FilterConfig",
    "FilteredController",
    "PriorBarrierFilter",
    "SafetyFilter",
    "edge_rows",
    "filter_reads_sensing",
    "register_filter",
]


#: the ``dcbf`` filter's barrier: Wang et al.'s braking-distance barrier with a smaller clearance, a larger gain and
#: a larger assumed deceleration than the dCBF-QP baseline's (margin 0.05 m, gamma 5, 2.5 m/s^2), chosen on
#: validation episodes (seed 777, N = 512 to 4096; docs/safety_filters.md): the policy already steers around its
#: neighbours, so the filter need act only late
DCBF_FILTER_BARRIER = BarrierConfig(margin=0.02, gamma=50.0, brake_accel=3.0)
#: the ``dcbf`` filter's look-ahead (s) under the realized acceleration: the attitude loop's lag (docs)
DCBF_FILTER_LOOKAHEAD = 0.05
#: the per-agent QP solvers of the ``cbf`` and ``prior`` filters (``FilterConfig.qp_solver``), the default first: the
#: exact batched dual active-set method and the interior-point method (:func:`~egcbf.algo.edge_qp.edge_qp_commands`)
QP_SOLVERS = ("active_set", "ipm")


@dataclass(frozen=True)
class FilterConfig:
    """Settings of a run-time filter (module doc).

    Attributes:
        kind: ``"cbf"``, ``"prior"`` or ``"dcbf"``.
        alpha: class-K gain (1/s) of the per-edge condition ``db/dt + alpha (b - margin) >= 0`` (``cbf``, ``prior``).
        margin: barrier offset (m): the filter keeps ``b >= margin`` (``cbf``, ``prior``; negative: closer than the
            barrier's own zero level).
        penalty: slack cost ``1/2 w2 s^2 + w1 s`` (s in m/s^2), as the dCBF-QP's.
        brake_gain: an agent whose QP fails gets ``a = -brake_gain v`` (within the box's inscribed ball).
        slack_tol: a solution "needs slack" above this (m/s^2); also the tolerance of the solution check.
        active_tol: an agent's command counts as changed by the filter above this (m/s^2).
        barrier: the hand-crafted pairwise barrier of the ``dcbf`` filter (``DCBF_FILTER_BARRIER``).
        lookahead: (s) the ``dcbf`` filter's barriers read every agent ``lookahead`` seconds ahead under the
            acceleration it realized over the last step (:meth:`~.dcbf_qp.DecentralizedCBFQP.filter`;
            ``DCBF_FILTER_LOOKAHEAD``; 0: the current state; ``cbf`` and ``prior`` ignore it).
        obstacle_sensing: where the ``dcbf`` filter's obstacle rows come from: ``"map"`` (the obstacle map's spheres,
            default) or ``"lidar"`` (each agent's own LiDAR hits as point obstacles: the sensing of ``cbf`` and
            ``prior``, whose rows always read the LiDAR).
        lidar_hits: with ``obstacle_sensing = "lidar"``, what each hit stands for in the ``dcbf`` filter's rows:
            ``"plane"`` (default, the plane through the hit normal to the ray) or ``"point"`` (a point obstacle)
            (:func:`~egcbf.robots.quadrotor.barriers.hit_constraints`; docs/safety_filters.md measures both).
        qp_solver: how ``cbf`` and ``prior`` solve their per-agent QPs (:data:`QP_SOLVERS`): ``"active_set"``
            (default; the exact batched dual active-set method,
            :func:`egcbf.qp.dense_active_set.solve_dense_batch_active_set`) or ``"ipm"`` (the batched interior-point
            method, :func:`egcbf.qp.dense_qp.solve_dense_batch_ipm`: within 1e-7 m/s^2 of it on most QPs, up to
            about 1e-4 on degenerate ones, some of which it reports unsolved, so that the agent brakes; slower:
            docs/benchmarks.md). ``None`` (the field's default) is the filter's default; the ``dcbf`` filter has its
            own solver and refuses any other value (``SafetyFilter.qp_solvers``).
    """

    kind: str = "cbf"
    alpha: float = 1.0
    margin: float = 0.0
    penalty: SlackPenalty = field(default_factory=SlackPenalty)
    brake_gain: float = BRAKE_GAIN
    slack_tol: float = SLACK_TOL
    active_tol: float = 1e-3
    barrier: BarrierConfig = DCBF_FILTER_BARRIER
    lookahead: float = DCBF_FILTER_LOOKAHEAD
    obstacle_sensing: str = "map"
    lidar_hits: str = "plane"
    qp_solver: str | None = None

    @classmethod
    def for_kind(
        cls,
        kind: str,
        alpha: float | None = None,
        margin: float | None = None,
        obstacle_sensing: str = "map",
        lidar_hits: str = "plane",
        qp_solver: str | None = None,
    ) -> FilterConfig:
        """The filter ``kind`` with its defaults, ``alpha`` and ``margin`` overriding its class-K gain and its
        clearance: ``alpha``, ``margin`` for ``cbf`` and ``prior``; the barrier's ``gamma``, ``margin`` for ``dcbf``;
        ``obstacle_sensing`` the ``dcbf`` filter's obstacle rows (``"map"`` or ``"lidar"``) and ``lidar_hits`` what
        one LiDAR hit stands for in them (``"plane"`` or ``"point"``); ``qp_solver`` the QP solver of ``cbf`` and
        ``prior`` (``None``: the filter's default)."""
        if kind not in FILTER_CLASSES:
            raise ValueError(f"FilterConfig.kind must be one of {FILTERS[1:]}, got {kind!r}")
        sensing = {"obstacle_sensing": obstacle_sensing, "lidar_hits": lidar_hits}
        if qp_solver is not None:  # (only then: a filter without a choice of solver refuses the field)
            sensing["qp_solver"] = qp_solver
        return FILTER_CLASSES[kind].make_config(cls, kind, alpha, margin, sensing)

    def settings(self) -> dict:
        """What a result records of the filter (``egcbf eval``'s run.json, ``egcbf reproduce``'s cells): its gain
        and clearance as the filter reads them (the barrier's for ``dcbf``)."""
        return FILTER_CLASSES[self.kind].settings(self)

    def __post_init__(self) -> None:
        if self.kind not in FILTERS or self.kind == "none":
            raise ValueError(f"FilterConfig.kind must be one of {FILTERS[1:]}, got {self.kind!r}")
        if not (math.isfinite(self.alpha) and self.alpha > 0):
            raise ValueError(f"FilterConfig.alpha must be positive and finite, got {self.alpha!r}")
        if not math.isfinite(self.margin):
            raise ValueError(f"FilterConfig.margin must be finite, got {self.margin!r}")
        if self.obstacle_sensing not in OBSTACLE_SENSING:
            raise ValueError(f"FilterConfig.obstacle_sensing must be one of {OBSTACLE_SENSING}, got "
                             f"{self.obstacle_sensing!r}")  # fmt: skip
        check_lidar_hits("FilterConfig", self.obstacle_sensing, self.lidar_hits)
        if not (math.isfinite(self.lookahead) and self.lookahead >= 0):
            raise ValueError(f"FilterConfig.lookahead must be >= 0, got {self.lookahead!r}")
        for name in ("brake_gain", "slack_tol", "active_tol"):
            if not getattr(self, name) > 0:
                raise ValueError(f"FilterConfig.{name} must be > 0, got {getattr(self, name)!r}")
        rows = FILTER_CLASSES.get(self.kind)
        solvers = rows.qp_solvers if rows is not None else QP_SOLVERS
        if self.qp_solver is None:
            if solvers:  # the filter's default (frozen: set once, here)
                object.__setattr__(self, "qp_solver", solvers[0])
        elif not solvers:
            raise ValueError(f"FilterConfig.qp_solver: the {self.kind!r} filter solves its QPs with its own solver; "
                             f"leave qp_solver None, got {self.qp_solver!r}")  # fmt: skip
        elif self.qp_solver not in solvers:
            raise ValueError(f"FilterConfig.qp_solver must be one of {solvers} for the {self.kind!r} filter, got "
                             f"{self.qp_solver!r}")  # fmt: skip


class SafetyFilter:
    """A run-time filter's rows as a plug-in (module doc): registered under its ``kind`` (:func:`register_filter`),
    built by :class:`FilteredController` from a :class:`FilterConfig` of that kind.

    Given every agent's proposed acceleration ``a_pi`` ``(B, N, 3)`` (float64, world frame), a filter returns the
    safe accelerations ``a`` (same shape), optionally the control ``u`` that realizes them (``None``: the
    acceleration interface's attitude loop tracks ``a``), and its counts (``num_slack``, ``num_failed``,
    ``max_slack``, ``slack_mask`` / ``failed_mask`` ``(B, N)``).
    """

    #: the name it is registered under (``FilterConfig.kind``, ``METHOD:KIND``)
    kind: ClassVar[str] = ""
    #: whether its rows read a checkpoint's CBF network
    needs_cbf: ClassVar[bool] = False
    #: whether its rows read the agents' graph (built anyway with a policy)
    uses_graph: ClassVar[bool] = True
    #: whether it reads every agent's realized acceleration (``FilterConfig.lookahead``)
    uses_lookahead: ClassVar[bool] = False
    #: the channels of ``state.sensing`` its rows perceive (:func:`egcbf.faults.sensing.unread_faults`)
    rows_read: ClassVar[Any] = True
    #: the QP solvers it offers (``FilterConfig.qp_solver``), its default first; empty: it has its own solver and
    #: refuses the setting (which then stays ``None`` and out of its :meth:`settings`)
    qp_solvers: ClassVar[tuple[str, ...]] = ()

    def __init__(self, config: FilterConfig, model_config: ModelConfig, cbf: CBFNet | None = None):
        self.config, self.model_config, self.cbf = config, model_config, cbf
        #: what this instance's rows perceive (may depend on its settings)
        self.reads_sensing = self.rows_read

    @classmethod
    def make_config(cls, config_cls, kind: str, alpha, margin, sensing: dict) -> FilterConfig:
        """:meth:`FilterConfig.for_kind` of this filter: ``alpha`` and ``margin`` (``None``: the defaults) override
        its class-K gain and clearance."""
        given = {k: v for k, v in (("alpha", alpha), ("margin", margin)) if v is not None}
        return config_cls(kind=kind, **sensing, **given)

    @staticmethod
    def settings(config: FilterConfig) -> dict:
        """What a result records of ``config`` (:meth:`FilterConfig.settings`)."""
        return {"alpha": config.alpha, "margin": config.margin}

    def __call__(self, state, s, env_config, graph, itf, a_pi, accel) -> tuple[Tensor, Tensor | None, dict]:
        """``(a, u or None, info)`` for the proposals ``a_pi`` (class doc); ``state`` as the controller got it, ``s``
        in the policy's dtype and device, ``graph`` the agents' graph (``None`` if neither the policy nor the rows
        read it), ``itf`` the acceleration interface, ``accel`` the realized accelerations or ``None``."""
        raise NotImplementedError(f"{type(self).__name__} must implement __call__")


#: filter kind -> class (:func:`register_filter`); the kinds are :data:`FILTERS` (``"none"`` aside)
FILTER_CLASSES: dict[str, type[SafetyFilter]] = {}


def register_filter(cls: type[SafetyFilter]) -> type[SafetyFilter]:
    """Register a :class:`SafetyFilter` subclass under its ``kind`` (a class decorator); its kind must be one of
    :data:`FILTERS`, the names the command line and the controller names parse."""
    if not (isinstance(cls, type) and issubclass(cls, SafetyFilter)) or cls.kind not in FILTERS[1:]:
        raise ValueError(f"register_filter needs a SafetyFilter whose kind is one of {FILTERS[1:]}, got {cls!r}")
    FILTER_CLASSES[cls.kind] = cls
    return cls


@register_filter
class EdgeBarrierFilter(SafetyFilter):
    """``"cbf"``: the checkpoint's learned per-edge barriers, one linear row per edge (module doc)."""

    kind = "cbf"
    needs_cbf = True
    qp_solvers = QP_SOLVERS

    @staticmethod
    def settings(config: FilterConfig) -> dict:
        """Its gain, clearance and QP solver (recorded so that the results of one are not reused for the other:
        their commands differ by the IPM's tolerance, and where it gives up on a degenerate QP)."""
        return {"alpha": config.alpha, "margin": config.margin, "qp_solver": config.qp_solver}

    def __call__(self, state, s, env_config, graph, itf, a_pi, accel):
        cfg, mc = self.config, self.model_config
        a, info = edge_qp_commands(
            graph, s.x, itf, a_pi, alpha=cfg.alpha, margin=cfg.margin, cbf=self.cbf, distance=mc.cbf_distance,
            horizon=mc.closest_approach_horizon, penalty=cfg.penalty, brake_gain=cfg.brake_gain,
            slack_tol=cfg.slack_tol, solver=cfg.qp_solver,
        )  # fmt: skip
        return a, None, info


@register_filter
class PriorBarrierFilter(EdgeBarrierFilter):
    """``"prior"``: the same rows from the CBF head's untrained prior (module doc)."""

    kind = "prior"
    needs_cbf = False

    def __init__(self, config: FilterConfig, model_config: ModelConfig, cbf: CBFNet | None = None):
        super().__init__(config, model_config, None)


@register_filter
class BrakingBarrierFilter(SafetyFilter):
    """``"dcbf"``: the dCBF-QP's hand-crafted braking-distance barriers with the filter's own settings and a
    look-ahead under the realized accelerations (module doc)."""

    kind = "dcbf"
    uses_graph = False
    uses_lookahead = True
    rows_read = DecentralizedCBFQP.reads_sensing

    def __init__(self, config: FilterConfig, model_config: ModelConfig, cbf: CBFNet | None = None):
        super().__init__(config, model_config, None)
        self.qp = DecentralizedCBFQP(
            barrier=config.barrier, penalty=config.penalty, brake_gain=config.brake_gain,
            obstacle_sensing=config.obstacle_sensing, lidar_hits=config.lidar_hits,
        )  # fmt: skip
        self.reads_sensing = self.qp.reads_sensing

    @classmethod
    def make_config(cls, config_cls, kind: str, alpha, margin, sensing: dict) -> FilterConfig:
        changes = {k: v for k, v in (("gamma", alpha), ("margin", margin)) if v is not None}
        try:
            return config_cls(kind=kind, barrier=replace(DCBF_FILTER_BARRIER, **changes), **sensing)
        except ValueError as err:  # name the filter's fields, not the barrier's
            raise ValueError(str(err).replace("BarrierConfig.gamma", "FilterConfig.alpha").replace(
                "BarrierConfig.margin", "FilterConfig.margin")) from None  # fmt: skip

    @staticmethod
    def settings(config: FilterConfig) -> dict:
        b = config.barrier
        lidar = (
            {"obstacle_sensing": "lidar", "lidar_hits": config.lidar_hits} if config.obstacle_sensing == "lidar" else {}
        )
        return {"barrier": b.kind, "gamma": b.gamma, "margin": b.margin, "brake_accel": b.brake_accel, **lidar}

    def __call__(self, state, s, env_config, graph, itf, a_pi, accel):
        u, qinfo = self.qp.filter(state, env_config, a_pi.cpu().numpy(), self.config.lookahead, accel)
        a = torch.as_tensor(qinfo["a_safe"], dtype=torch.float64, device=a_pi.device)
        info = {k: qinfo[k] for k in ("num_slack", "num_failed", "max_slack")}
        info["slack_mask"] = qinfo["slack"] > self.qp.config.slack_tol
        info["failed_mask"] = qinfo["failed"]
        return a, u, info


#: per filter kind, the channels of ``state.sensing`` (:data:`egcbf.faults.sensing.CHANNELS`) that the filter's rows
#: perceive (module doc)
READS_SENSING = {kind: cls.rows_read for kind, cls in FILTER_CLASSES.items()}


def filter_reads_sensing(kind: str, has_policy: bool):
    """A filtered controller's ``reads_sensing`` (:func:`egcbf.faults.sensing.unread_faults`): every channel with a
    policy (it builds its graph from what the agents perceive, LiDAR included), else its filter rows' channels
    (:data:`READS_SENSING`)."""
    if kind not in READS_SENSING:
        raise ValueError(f"unknown filter kind {kind!r}; choose from {sorted(READS_SENSING)}")
    return True if has_policy else READS_SENSING[kind]


class FilteredController:
    """A learned policy whose commands pass through a decentralized run-time filter (module doc):
    ``u, info = ctrl(state, env_config)``, the evaluation controller's signature. ``policy = None`` filters the
    nominal controller's command instead (the ablation that shows what the policy adds; ``cbf`` then needs ``cbf``
    and ``model_config``: the per-edge QP target of ``TrainConfig.qp_constraints = "edges"`` run as a controller).

    ``info``: ``u_ref`` (the nominal controller's control, for the reward as for the policy alone), ``qp_ms``,
    ``num_slack`` (agents whose QP needed slack), ``num_failed`` (agents given the braking fallback),
    ``num_active`` (agents whose command the filter changed by more than ``active_tol``), ``num_agents``, and per
    agent ``slack_mask`` / ``failed_mask`` / ``active_mask`` ``(B, N)`` numpy bool (its QP needed slack / it
    braked / its command was changed), and ``accel_command`` ``(B, N, 3)`` the filtered world acceleration (m/s^2,
    braking included) that ``u`` tracks (what a setpoint-flying low level flies instead: ``egcbf eval --low-level``).
    """

    name = "filtered"

    def __init__(
        self,
        policy: PolicyNet | None,
        model_config: ModelConfig | None,
        config: FilterConfig,
        cbf: CBFNet | None = None,
    ):
        rows = FILTER_CLASSES[config.kind]
        if policy is None:  # the nominal controller's command behind the filter (an ablation: what the policy adds)
            if rows.needs_cbf and (cbf is None or model_config is None):
                raise ValueError(
                    f"the {config.kind!r} filter reads a checkpoint's CBF: pass its CBF network and model config "
                    "(cbf=..., model_config=...) to filter the nominal command with it"
                )
            model_config = model_config or TrainConfig.preset("egcbf+", "cpu").model  # the prior's D and horizon
        elif model_config.interface != "accel":
            raise ValueError(
                f"run-time filters act on the acceleration command; this policy's interface is "
                f"{model_config.interface!r}"
            )
        if rows.needs_cbf and cbf is None:
            raise ValueError(f"the {config.kind!r} filter needs the checkpoint's CBF network")
        self.policy, self.model_config, self.config, self.cbf = policy, model_config, config, cbf
        #: the filter's rows (:class:`SafetyFilter`)
        self.rows = rows(config, model_config, cbf)
        self._last: tuple[int, np.ndarray] | None = None  # (step, velocities) of the previous call: lookahead only
        # a policy builds its graph from everything the agents perceive; the nominal command, what the rows read
        self.reads_sensing = True if policy is not None else self.rows.reads_sensing

    @torch.no_grad()
    def __call__(self, state: SwarmState, env_config: EnvConfig) -> tuple[Tensor, dict]:
        t0 = time.perf_counter()
        if self.policy is not None:
            p = next(self.policy.parameters())
            s = state if state.x.dtype == p.dtype and state.x.device == p.device else state.to(p.device, dtype=p.dtype)
        else:
            s = state
        robot = env_config.make_robot()
        itf = make_interface("accel", robot)
        graph = build_graph(s, env_config) if self.policy is not None or self.rows.uses_graph else None
        if self.policy is None:
            c_pi = itf.nominal(s.x, s.goals)
        else:
            c_pi, _ = policy_command(self.policy, self.model_config, itf, graph, s.x, s.goals)
        a_pi = (itf.accel_unit * c_pi).to(torch.float64)
        u_nom = robot.nominal_control(s.x, s.goals)
        t1 = time.perf_counter()
        accel = self._realized_acceleration(s, env_config) if self.rows.uses_lookahead else None
        a, u, info = self.rows(state, s, env_config, graph, itf, a_pi, accel)
        if u is None:
            u = itf.apply(s.x, (a / itf.accel_unit).to(s.x.dtype))
        active = (a - a_pi).norm(dim=-1) > self.config.active_tol
        info.update(
            u_ref=u_nom.to(state.x.dtype).to(state.x.device),
            qp_ms=1e3 * (time.perf_counter() - t1),
            ctrl_ms=1e3 * (time.perf_counter() - t0),
            num_active=int(active.sum()),
            num_agents=int(active.numel()),
            active_mask=active.cpu().numpy(),
            a_safe=a,
            a_policy=a_pi,
            accel_command=a.to(state.x.dtype).to(state.x.device),
        )
        return u.to(state.x.dtype).to(state.x.device), info

    def _realized_acceleration(self, s: SwarmState, env_config: EnvConfig) -> np.ndarray | None:
        """Every agent's acceleration over the last control step, ``(v_t - v_{t-1}) / dt`` ``(B, N, 3)``, from the
        velocities seen at the previous call (each agent senses its neighbours' velocities every step; under message
        faults a neighbour's comes with its message instead, :meth:`egcbf.faults.Sensing.received`); ``None`` at an
        episode's first step or when the previous call was another swarm. Only with ``lookahead``."""
        if not self.config.lookahead:
            return None
        v = s.x[..., 12:15].detach().to(torch.float64).cpu().numpy()
        prev, self._last = self._last, (s.t, v)
        if prev is None or prev[0] != s.t - 1 or prev[1].shape != v.shape:
            return None
        return (v - prev[1]) / env_config.dt
