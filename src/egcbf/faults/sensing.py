"""What the agents perceive under faults: their LiDAR scans and the messages on the graph's edges.

A :class:`Sensing` rides on the observed :class:`egcbf.env.SwarmState` that :class:`egcbf.faults.FaultProcess` hands
to the controller (``state.sensing``); :func:`egcbf.env.graph.build_graph` takes the scan from :meth:`Sensing.scan` and
passes the graph it built through :meth:`Sensing.messages`. So every controller that builds its graph from the state
(the learned policies and the filters around them) perceives the faults, with no change to the controller.

* **LiDAR**: the rays are cast from the agents' *true* positions and headings (a sensor measures the world as it
  is) and placed around the agents' *estimated* positions (where the agent believes it is), so under state-estimate
  noise alone the scan's vectors to the obstacles stay exact; each ray's range gets its Gaussian error
  (``lidar_noise``) and each ray's return is lost with probability ``lidar_drop``, before the closest
  ``lidar_max_hits`` returns are kept (a sensor's returns, then the scan's processing).
* **Messages**: an agent-to-agent edge carries the sender's broadcast estimate; with ``msg_delay = k`` it is the
  estimate of ``k`` steps ago (sender features and position), and the edge vector is that position minus the
  receiver's current estimate; an edge whose delayed neighbour lies outside the communication radius is dropped, and
  each edge is lost with probability ``msg_loss`` in each step (with ``msg_burst``, in runs: whole blocks of steps
  per link). The receivers' handling (:data:`RECEIVER_FIELDS`):
  with ``msg_hold = H`` a lost message is replaced by the last one received on that link within ``H`` steps (so
  one link's message can be older than another's: the graph then gives each such edge its own sender row), and
  with ``msg_predict`` every message is moved to the present at the velocity it carries, over its age.
  :meth:`Sensing.received` decides which directed links (receiver, sender) carry a message and what it carries;
  the graph (:meth:`Sensing.messages`) and the decentralized CBF-QP (:class:`~.dcbf_qp.DecentralizedCBFQP`) both
  read it, so they lose the same messages.

A controller declares the channels it perceives in its ``reads_sensing`` attribute (:data:`CHANNELS`,
:func:`unread_faults`): ``True`` for every channel (it builds its whole graph from the observed state), or a
collection of channel names; :func:`egcbf.evaluate.episodes.run_episodes` refuses a fault on a channel the controller
would ignore."""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..env.config import EnvConfig
from ..env.graph import KIND_AGENT, SwarmGraph, agent_features, edge_vectors
from ..env.lidar import LidarScan
from ..env.obstacles import Obstacles
from ..env.swarm import cast_lidar
from ..robots import Robot
from . import draws
from .spec import CHANNELS, INERT_FIELDS, FaultConfig

__all__ = ["CHANNELS", "STREAMS", "Sensing", "unread_faults", "unread_fields"]

#: the random streams of the faults (the second number of every draw's address; :mod:`egcbf.faults.draws`)
STREAMS = {"pos": 1, "vel": 2, "loss": 3, "lidar": 4, "lidar_drop": 5, "gain": 6, "bias": 7, "noncoop": 8,
           "gust": 9, "burst": 10}  # fmt: skip


def unread_faults(controller, faults: FaultConfig) -> tuple[str, ...]:
    """The active fault fields (of :data:`CHANNELS`) that ``controller`` would ignore, in :data:`CHANNELS` order.

    ``controller.reads_sensing`` says which channels of ``state.sensing`` it honours: ``True`` every one, a
    collection of :data:`CHANNELS` names those, absent or ``False`` none.
    """
    return unread_fields(getattr(controller, "reads_sensing", False), faults, type(controller).__name__)


def unread_fields(declared, faults: FaultConfig, who: str = "controller") -> tuple[str, ...]:
    """:func:`unread_faults` from a ``reads_sensing`` declaration itself (no controller built: planning a sweep)."""
    if declared is True:
        return ()
    read = set(declared or ())
    unknown = sorted(read - set(CHANNELS))
    if unknown:
        raise ValueError(f"{who}.reads_sensing: unknown channels {unknown}; known: {list(CHANNELS)}")
    return tuple(
        name
        for channel, names in CHANNELS.items()
        if channel not in read
        for name in names
        if getattr(faults, name) > 0
    )


@dataclass
class Sensing:
    """The perception of one step (see the module doc).

    Attributes:
        faults: the fault levels.
        robot: the agents' robot.
        seeds: ``(B,)`` int64, the episode seed of each environment (the root of every draw's address).
        t: the step.
        x_true: ``(B, N, S)`` the true states (where the rays start).
        x_seen: ``(B, N, S)`` the agents' estimates (what they broadcast and where they place their scans).
        x_sent: ``(B, N, S)`` the estimates the messages of this step carry (``x_seen`` of ``msg_delay`` steps ago).
        obstacles: the true obstacles.
        history: the estimates of the steps before, newest first (``history[k]``: ``x_seen`` of step ``t - k``,
            ``history[0] = x_seen``), as many as ``msg_delay + msg_hold + 2`` once the episode is that old (the
            oldest message's state and the one before, for the acceleration it carries); empty: ``(x_seen,)`` (no
            hold, no acceleration known).
        dt: the control period (s), for ``msg_predict``.
        x_placed: ``(B, N, S)`` where the agents place their scans: their current estimates, before any prediction
            over an actuation delay (``act_predict``: ``x_seen`` is then the predicted state, and a static obstacle
            stays where it is in the world); ``None``: ``x_seen``.
    """

    faults: FaultConfig
    robot: Robot
    seeds: Tensor
    t: int
    x_true: Tensor
    x_seen: Tensor
    x_sent: Tensor
    obstacles: Obstacles
    history: tuple[Tensor, ...] = ()
    dt: float = 0.0
    x_placed: Tensor | None = None

    # -------------------------------------------------------------------------------------------------- LiDAR
    def scan(self, config: EnvConfig) -> LidarScan:
        """The scan the agents get (dtype of the estimates): cast from the true poses, every ray's return with its
        range error and lost with probability ``lidar_drop`` before the closest ``lidar_max_hits`` are kept (a
        sensor's returns, :meth:`ray_faults`), the hits then placed around the agents' estimates
        (:attr:`x_placed`)."""
        robot, f = self.robot, self.faults
        p_true = robot.positions(self.x_true)
        faulty = f.lidar_noise > 0 or f.lidar_drop > 0
        truth = cast_lidar(config, p_true, robot.heading(self.x_true), self.obstacles,
                           self.ray_faults if faulty else None)  # fmt: skip
        rel = truth.points - p_true[:, :, None]
        placed = self.x_seen if self.x_placed is None else self.x_placed
        p_seen = robot.positions(placed)[:, :, None].to(truth.points.dtype)
        points = torch.where(truth.valid[..., None], p_seen + rel, p_seen.expand_as(rel))
        dtype = self.x_seen.dtype
        return LidarScan(points.to(dtype), truth.valid, truth.distance.to(dtype))

    def ray_faults(self, agent: Tensor, ray: Tensor, distance: Tensor) -> tuple[Tensor, Tensor]:
        """The LiDAR's faults on single returns (:data:`egcbf.env.lidar.RayFaults`): ``agent`` ``(R,)`` flat rows
        ``b * N + i``, ``ray`` ``(R,)`` the ray indices, ``distance`` ``(R,)`` the true ranges (m). Returns the
        measured ranges (Gaussian error of std ``lidar_noise``, clamped at 0; draw ``(seed, "lidar", t, i, ray)``)
        and which returns arrive (draw ``(seed, "lidar_drop", t, i, ray) >= lidar_drop``)."""
        f = self.faults
        n = self.x_true.shape[1]
        address = (self.seeds.to(agent.device)[agent // n], self.t, agent % n, ray)
        if f.lidar_noise > 0:
            err = f.lidar_noise * draws.normal(STREAMS["lidar"], *address, dtype=distance.dtype)
            distance = (distance + err).clamp_min(0)
        arrived = torch.ones_like(agent, dtype=torch.bool)
        if f.lidar_drop > 0:
            arrived = draws.uniform(STREAMS["lidar_drop"], *address) >= f.lidar_drop
        return distance, arrived

    # ----------------------------------------------------------------------------------------------- messages
    @property
    def message_faults(self) -> bool:
        """Whether messages are lost or late (else every agent hears its neighbours' current estimates, and the
        receivers' handling has nothing to do)."""
        return any(getattr(self.faults, n) > 0 for n in CHANNELS["messages"] if n not in INERT_FIELDS)

    def _arrives(self, address: tuple[Tensor, Tensor, Tensor], t: int) -> Tensor:
        """Whether the message of step ``t`` on each link ``address = (seed, receiver, sender)`` (local indices)
        arrives: its draw at ``("loss", seed, t, receiver, sender)`` is ``>= msg_loss``; with ``msg_burst = L >= 2``
        the draw of the link's block of ``L`` steps instead, ``("loss", seed, (t + phase) // L, receiver, sender)``,
        ``phase`` uniform in ``0 .. L - 1`` per link (``("burst", seed, receiver, sender)``)."""
        f = self.faults
        step: Tensor | int = t
        if f.msg_burst > 1:
            phase = (draws.uniform(STREAMS["burst"], *address) * f.msg_burst).long()
            step = torch.div(t + phase, f.msg_burst, rounding_mode="floor")
        return draws.uniform(STREAMS["loss"], address[0], step, *address[1:]) >= f.msg_loss

    @property
    def delay_age(self) -> int:
        """Steps since the messages of this step were sent: ``msg_delay``, or fewer at an episode's first steps."""
        return min(self.faults.msg_delay, len(self.history) - 1) if self.history else self.faults.msg_delay

    def _moved_on(self, states: Tensor, steps: Tensor | int) -> Tensor:
        """``states`` ``(E, S)`` as the receiver uses them: with ``msg_predict`` moved on at their velocity over
        ``steps`` control steps (an int, or ``(E,)`` per row), else unchanged."""
        if not self.faults.msg_predict:
            return states
        dt = (steps.to(states.dtype) * self.dt)[:, None] if isinstance(steps, Tensor) else steps * self.dt
        return self.robot.perturbed(states, dt * self.robot.velocities(states), None)

    def sent_states(self, like: Tensor) -> Tensor:
        """``(B N, S)``: every agent's message of this step as its receivers use it (``x_sent``, moved on over
        :attr:`delay_age` with ``msg_predict``), in the dtype and on the device of ``like``."""
        sent = self.x_sent.reshape(-1, self.x_sent.shape[-1]).to(device=like.device, dtype=like.dtype)
        return self._moved_on(sent, self.delay_age)

    @property
    def per_link(self) -> bool:
        """Whether the messages of one sender can differ between its links (held messages of different ages), so
        that every link carries its own sender state."""
        return self.faults.msg_hold > 0 and self.faults.msg_loss > 0

    def received(
        self,
        receivers: Tensor,
        senders: Tensor,
        comm_radius: float,
        like: Tensor | None = None,
        accelerations: bool = False,
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """Which candidate directed links carry a message in this step, and what each message tells its receiver.

        Args:
            receivers, senders: ``(E,)`` long, the agents of each candidate link ``receiver <- sender`` as flat rows
                ``b * N + i`` of the same environment ``b`` (the graph's receiver rows). Candidates are the pairs
                within ``comm_radius`` of each other's *current* estimates (the neighbour search of the graph and of
                the QP).
            comm_radius: the communication radius (m).
            like: the dtype and device of the states returned (default: ``x_sent``'s).
            accelerations: also tell the acceleration each message carries (else ``accel`` is ``None``).

        Returns:
            ``keep`` ``(E,)`` bool on the device of ``receivers``: the link has a message, i.e. the one of this step
            is not lost (its draw at address ``("loss", seed, t, i, j)`` is ``>= msg_loss``, ``i, j`` the local
            indices of receiver and sender) or, with ``msg_hold = H``, one of the ``H`` steps before was not (the
            newest is used); and, with a delay or a held message, the sender's position it carries lies within
            ``comm_radius`` of the receiver's current estimate.
            ``states`` ``(E, S)``: the sender's state as the receiver uses it, world frame: its estimate of
            ``msg_delay`` steps before the message was sent (``x_sent`` for a message of this step), moved to the
            present at its velocity with ``msg_predict``.
            ``accel`` ``(E, d)`` float64: the acceleration the message carries, its sender's over the step before
            that estimate (``(v_{t-a} - v_{t-a-1}) / dt`` of the sender's estimates, ``a`` the message's age; world
            frame, m/s^2), zero where that earlier estimate is not in :attr:`history` (an episode's first step): what
            a receiver knows of a neighbour's acceleration (the look-ahead of the ``dcbf`` filter).
        """
        f, robot = self.faults, self.robot
        b, n = self.x_seen.shape[:2]
        like = self.x_sent if like is None else like
        history = self.history or (self.x_seen,)
        if self.per_link and not self.history:
            raise ValueError("Sensing.received: held messages (msg_hold with msg_loss) need the estimates of the steps "
                             "before (history); FaultProcess.observe passes them")  # fmt: skip
        keep = torch.ones(receivers.shape, dtype=torch.bool, device=receivers.device)
        held = torch.zeros(receivers.shape, dtype=torch.long, device=receivers.device)  # steps since it was sent
        if f.msg_loss > 0:
            seeds = self.seeds.to(receivers.device)[receivers // n]
            address = (seeds, receivers % n, senders % n)
            keep = self._arrives(address, self.t)
            for k in range(1, min(f.msg_hold, self.t) + 1):  # the newest message of the last msg_hold steps
                older = ~keep & self._arrives(address, self.t - k)
                held[older] = k
                keep |= older
        src = senders.to(like.device)
        if self.per_link:
            age = (held.to(like.device) + f.msg_delay).clamp_max(len(history) - 1)
            stacked = torch.stack(history).reshape(len(history) * b * n, -1)
            states = self._moved_on(stacked[age * (b * n) + src].to(dtype=like.dtype), age)
        else:
            age = torch.full_like(src, self.delay_age)
            states = self.sent_states(like)[src]
        accel = self._carried_acceleration(history, src, age) if accelerations else None
        if f.msg_delay > 0 or self.per_link:
            seen = self.x_seen.reshape(b * n, -1).to(device=like.device, dtype=like.dtype)
            gap = torch.linalg.vector_norm(robot.positions(states) - robot.positions(seen)[receivers.to(like.device)],
                                           dim=-1)  # fmt: skip
            keep &= (gap < comm_radius).to(receivers.device)
        return keep, states, accel

    def _carried_acceleration(self, history: tuple[Tensor, ...], src: Tensor, age: Tensor) -> Tensor:
        """``(E, d)`` float64: the acceleration of sender rows ``src`` over the step before their estimate of
        ``age`` steps ago (``(E,)`` each), from ``history``; zero where the step before is not in it."""
        robot, k = self.robot, len(history)
        if k < 2:
            return torch.zeros(src.shape[0], robot.dim, dtype=torch.float64, device=src.device)
        if not self.dt > 0:
            raise ValueError(f"Sensing.dt must be the control period (s) > 0 to tell accelerations, got {self.dt!r}")
        rows = src.to(history[0].device)
        stacked = torch.stack(history).reshape(k, -1, history[0].shape[-1])  # (K, B N, S)
        before = (age + 1).to(rows.device)
        now_v = robot.velocities(stacked[age.to(rows.device), rows]).to(torch.float64)
        before_v = robot.velocities(stacked[before.clamp_max(k - 1), rows]).to(torch.float64)
        accel = torch.where((before < k)[:, None], (now_v - before_v) / self.dt, torch.zeros_like(now_v))
        return accel.to(src.device)

    def messages(self, graph: SwarmGraph) -> SwarmGraph:
        """``graph`` (built from the estimates) with its agent-to-agent edges as the messages arrive
        (:meth:`received`): delayed, held and predicted senders, out-of-range and lost messages dropped. Where one
        sender's messages are the same on all its links (no hold), the sender's row is replaced; otherwise each
        agent-to-agent edge gets its own sender row, appended to ``x_src``."""
        if not self.message_faults:
            return graph
        m = graph.num_dst
        src, dst = graph.edge_index
        agent_edge = graph.edge_kind == KIND_AGENT
        arrived, states, _ = self.received(dst[agent_edge], src[agent_edge], graph.comm_radius, like=graph.x_src)
        keep = ~agent_edge
        keep[agent_edge] = arrived
        x_src, pos_src, edge_index = graph.x_src, graph.pos_src, graph.edge_index
        src_kind, src_batch = graph.src_kind, graph.src_batch
        if self.per_link:
            rows = torch.arange(x_src.shape[0], x_src.shape[0] + states.shape[0], device=edge_index.device)
            edge_index = edge_index.clone()
            edge_index[0, agent_edge] = rows
            x_src = torch.cat((x_src, agent_features(self.robot, states)))
            pos_src = torch.cat((pos_src, self.robot.positions(states)))
            src_kind = torch.cat((src_kind, src_kind[src[agent_edge]]))
            src_batch = torch.cat((src_batch, src_batch[src[agent_edge]]))
        elif self.faults.msg_delay > 0 or self.faults.msg_predict:
            sent = self.sent_states(x_src)
            x_src = torch.cat((agent_features(self.robot, sent), x_src[m:]))
            pos_src = torch.cat((self.robot.positions(sent), pos_src[m:]))
        edge_index = edge_index[:, keep]
        edge_kind = graph.edge_kind[keep]
        edge_attr = edge_vectors(pos_src, graph.pos_dst, edge_index, edge_kind, graph.comm_radius)
        return replace(graph, x_src=x_src, pos_src=pos_src, edge_index=edge_index, edge_kind=edge_kind,
                       edge_attr=edge_attr, src_kind=src_kind, src_batch=src_batch)  # fmt: skip
