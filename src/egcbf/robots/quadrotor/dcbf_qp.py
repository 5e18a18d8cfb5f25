"""The quadrotor's decentralized CBF-QP (GCBF+'s dCBF-QP): one small QP per agent over its own acceleration, each
agent enforcing half of every pair row (:mod:`egcbf.robots.quadrotor.cbf_qp` has the shared configuration, the
two loops around the filter and the centralized QP; ``docs/baselines.md`` the derivation).

Under message faults (``state.sensing`` of :mod:`egcbf.faults` with ``msg_loss`` or ``msg_delay``) the agents know
their neighbours only from the messages they received (:meth:`egcbf.faults.Sensing.received`): agent ``i``'s half of
a pair row reads its own estimate and the neighbour's broadcast estimate, and a lost message removes the pair from
``i``'s QP only. The halves then no longer add up to the pair's condition: where only ``j`` heard ``i``, ``j`` keeps
its half and ``i`` none (and ``j`` cannot tell), and under delay the two halves read two different views of the pair;
so message faults cost the dCBF-QP its guarantee, not just its accuracy (docs/robustness.md measures how much; the
receivers' hold restores most one-way links).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from ...qp.constraints import Constraints
from ...qp.dense_qp import assemble_decentralized, solve_dense_batch, solve_dense_batch_ipm, verified
from .barriers import (
    agent_pairs,
    build_constraints,
    hit_constraints,
    perceived_constraints,
    prune_redundant,
    split_for_agents,
)
from .cbf_qp import _CBFQPBase, _Prepared

__all__ = ["DecentralizedCBFQP"]


class DecentralizedCBFQP(_CBFQPBase):
    """dCBF-QP: one QP per agent in ``(a_i, s_i)``; agent ``i`` enforces ``n . a_i >= b / 2`` for each neighbour
    (the other half is its neighbour's) and the whole obstacle rows. All ``B N`` QPs are solved in one batch by a
    batched interior-point method (:func:`egcbf.qp.dense_qp.solve_dense_batch_ipm`, on the device of
    ``state.x``; or proxsuite's ``dense.BatchQP`` + ``solve_in_parallel`` with ``dcbf_solver="proxsuite"``).

    Under message faults (``state.sensing``, :mod:`egcbf.faults`; module doc) agent ``i``'s pair rows come from its
    own perception: its estimate ``state.x[b, i]`` against what the message of each neighbour ``j`` on link
    ``(i, j)`` tells it (``sensing.x_sent[b, j]``, ``msg_delay`` steps old; or an older message held by the receiver,
    ``msg_hold``; moved to the present with ``msg_predict``), for the directed links that
    :meth:`egcbf.faults.Sensing.received` keeps; the obstacle rows read the agent's estimate and the obstacle map.

    ``info`` as :class:`CentralizedCBFQP`, counting per-agent QPs: ``num_slack`` agents whose slack exceeds
    ``slack_tol``, ``num_failed`` agents given the fallback; ``max_rows`` the padded row count; under message faults
    ``links`` ``(2, L)``, the directed links ``(receiver, sender)`` (flat agent rows ``b N + i``) whose messages
    arrived (their rows may then be pruned as unreachable).
    """

    name = "dcbf"
    #: the channels of ``state.sensing`` it perceives (:data:`egcbf.faults.sensing.CHANNELS`): the messages; its
    #: obstacle rows read the obstacle map, not a LiDAR scan
    reads_sensing = frozenset({"messages"})

    def __init__(self, config=None, **overrides):
        super().__init__(config, **overrides)
        if self.config.obstacle_sensing == "lidar":  # its obstacle rows then read each agent's own scan
            self.reads_sensing = frozenset({"messages", "lidar"})

    def __call__(self, state, env_config) -> tuple[Tensor, dict]:
        return self.filter(state, env_config)

    def filter(
        self,
        state,
        env_config,
        a_ref: np.ndarray | None = None,
        lookahead: float = 0.0,
        accel: np.ndarray | None = None,
    ) -> tuple[Tensor, dict]:
        """The dCBF-QP around a reference acceleration: each agent's QP keeps ``a_i`` closest to ``a_ref[b, i]``
        ``(B, N, 3)`` (world frame, m/s^2; ``None``: the nominal acceleration, the dCBF-QP baseline). Used as the
        ``dcbf`` run-time filter of a learned policy (:mod:`egcbf.control.filters`).

        ``lookahead`` (s): the barriers read every agent at its state ``lookahead`` seconds ahead under its
        current acceleration ``accel`` ``(B, N, 3)`` (m/s^2, world frame; ``None``: zero), ``p + T v + T^2 a / 2``
        and ``v + T a``: a new command acts only after the attitude loop has turned the thrust (~0.1 s), and until
        then the agents keep the acceleration they have (a predictor for the loop's lag). Under message faults an
        agent knows a neighbour only as its message carries it: its state and the acceleration it had then
        (:meth:`egcbf.faults.Sensing.received`), and predicts it with that acceleration."""
        t0, c0 = time.perf_counter(), time.process_time()
        cfg = self.config
        prep = self._prepare(state, env_config, a_ref)
        sensing = _message_sensing(state)
        p_now = prep.p
        if lookahead:
            acc = _accel_or_zero(accel, prep.v)
            prep.p = prep.p + lookahead * prep.v + 0.5 * lookahead**2 * acc
            prep.v = prep.v + lookahead * acc
        b, n = prep.p.shape[:2]
        m = b * n
        batch = np.repeat(np.arange(b), n)
        has_obs = any(c is not None and len(c) for c in prep.centers)
        from_map = has_obs and cfg.obstacle_sensing == "map"
        obstacles = (prep.centers, prep.radii) if from_map else (None, None)
        links = None
        if sensing is None:
            cons = build_constraints(
                prep.p.reshape(m, 3), prep.v.reshape(m, 3), prep.barrier, *obstacles, batch=batch, bounds=prep.bounds
            )
            owner, normal, rhs = split_for_agents(cons)
        else:
            links, sent_p, sent_v = self._perceived(prep, sensing, env_config, p_now.reshape(m, 3), batch, lookahead)
            cons = perceived_constraints(
                prep.p.reshape(m, 3), prep.v.reshape(m, 3), links, sent_p, sent_v, prep.barrier, *obstacles,
                batch=batch, bounds=prep.bounds,
            )  # fmt: skip
            owner, normal, rhs = split_for_agents(cons, num_agents=m)
        if has_obs and not from_map:
            hits = self._hit_rows(state, env_config, prep, m, cfg.lidar_hits)
            owner, normal, rhs = (np.concatenate(t) for t in zip((owner, normal, rhs), hits))
            cons = Constraints.cat([cons, hits[3]])
        bC = prep.bC.reshape(m, *prep.bC.shape[2:])
        blo, bhi = prep.blo.reshape(m, -1), prep.bhi.reshape(m, -1)
        qps = assemble_decentralized(prep.a_nom.reshape(m, 3), owner, normal, rhs, bC, blo, bhi, cfg.penalty)
        if cfg.dcbf_solver == "ipm":
            z, ok, _ = solve_dense_batch_ipm(qps, device=prep.x.device)
        elif cfg.dcbf_solver == "proxsuite":
            z, ok, _ = solve_dense_batch(qps, eps_abs=cfg.eps_abs, max_iter=max(cfg.max_iter, 1000))
        else:
            raise ValueError(f"unknown dcbf_solver {cfg.dcbf_solver!r}; choose 'ipm' or 'proxsuite'")
        a, s = z[:, :3], z[:, 3]
        tol = cfg.slack_tol
        bad = ~verified(qps, z, ok, tol)  # every agent's solution up to its slack (its own half-rows, its bounds)
        if bad.any():
            a = a.copy()
            a[bad] = self._brake(prep.v.reshape(m, 3)[bad], prep.bounds)
            s = np.where(bad, 0.0, s)
        a_safe = a.reshape(b, n, 3)
        qp_ms = 1e3 * (time.perf_counter() - t0)
        cpu_ms = 1e3 * (time.process_time() - c0)
        u = self._finish(prep, a_safe).to(state.x.dtype)
        info = {
            "qp_ms": qp_ms,
            "qp_cpu_ms": cpu_ms,
            "num_slack": int((s > tol).sum()),
            "num_failed": int(bad.sum()),
            "num_qps": m,
            "num_constraints": len(cons),
            "max_rows": int(qps.cbf_normal.shape[1]),
            "max_slack": float(s.max(initial=0.0)),
            "a_safe": a_safe,
            "a_nom": prep.a_nom,
            "failed": bad.reshape(b, n),  # per agent: its QP failed or its solution failed the check (it brakes)
            "slack": s.reshape(b, n),
        }
        if links is not None:
            info["links"] = links
        return u, info

    @staticmethod
    def _hit_rows(state, env_config, prep, m: int, lidar_hits: str):
        """Every agent's rows from its own LiDAR hits (``obstacle_sensing = "lidar"``): the scan as the agents get
        it (under LiDAR faults, :meth:`egcbf.faults.Sensing.scan`), each hit read as ``lidar_hits`` says (a plane
        or a point, :func:`~egcbf.robots.quadrotor.barriers.hit_constraints`) at the (look-ahead) state of the
        barriers; ``(owner, normal, rhs, constraints)``, redundant rows pruned."""
        sensing = state.sensing
        if sensing is not None:
            scan = sensing.scan(env_config)
        else:
            scan = env_config.scan(state.positions, state.robot.heading(state.x), state.obstacles)
        points = scan.points.detach().to(torch.float64).cpu().numpy().reshape(m, -1, 3)
        valid = scan.valid.detach().cpu().numpy().reshape(m, -1)
        cons = prune_redundant(hit_constraints(prep.p.reshape(m, 3), prep.v.reshape(m, 3), points, valid,
                                               prep.barrier, lidar_hits), prep.bounds)  # fmt: skip
        return cons.i, cons.normal, cons.rhs, cons

    @staticmethod
    def _perceived(
        prep: _Prepared, sensing, env_config, p_now: np.ndarray, batch: np.ndarray, lookahead: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the agents know of their neighbours under message faults (:meth:`egcbf.faults.Sensing.received`).

        Candidates are the neighbour pairs of the agents' current estimates ``p_now`` ``(M, 3)`` within the
        barrier's cull radius and the communication radius, in both directions: the radio's range, decided on the
        current estimates as the graph decides it (so graph and QP lose the same messages); what a receiver then
        knows of the sender is its message alone. Returns the directed links ``(receiver, sender)`` ``(2, L)`` whose
        messages arrived (flat agent rows ``b N + i``, sorted), and the sender's position and velocity as each
        link's message tells its receiver ``(L, 3)`` each (world frame, float64), ``lookahead`` seconds ahead under
        the acceleration the message carries.
        """
        comm = float(env_config.comm_radius)
        near = replace(prep.barrier, cull_radius=min(prep.barrier.cull_radius, comm))
        pairs = agent_pairs(p_now, near, batch)
        recv = np.concatenate((pairs[0], pairs[1]))
        send = np.concatenate((pairs[1], pairs[0]))
        keep, states, carried = sensing.received(torch.from_numpy(recv), torch.from_numpy(send), comm, like=prep.x,
                                                 accelerations=bool(lookahead))  # fmt: skip
        keep = keep.cpu().numpy()
        p = sensing.robot.positions(states).cpu().numpy()[keep]
        v = sensing.robot.velocities(states).cpu().numpy()[keep]
        recv, send = recv[keep], send[keep]
        order = np.lexsort((send, recv))
        links = np.stack((recv[order], send[order]))
        p, v = p[order], v[order]
        if lookahead:
            acc = carried.cpu().numpy()[keep][order]
            p = p + lookahead * v + 0.5 * lookahead**2 * acc
            v = v + lookahead * acc
        return links, p, v


def _accel_or_zero(accel: np.ndarray | None, like: np.ndarray) -> np.ndarray:
    """``accel`` as float64, or zeros shaped like ``like``."""
    return np.zeros_like(like) if accel is None else np.asarray(accel, dtype=np.float64)


def _message_sensing(state):
    """``state.sensing`` (:class:`egcbf.faults.Sensing`) when it loses or delays messages, else ``None``."""
    sensing = getattr(state, "sensing", None)
    if sensing is None or not sensing.message_faults:
        return None
    if tuple(sensing.x_sent.shape[:2]) != tuple(state.x.shape[:2]):
        raise ValueError(
            f"state.sensing is for {tuple(sensing.x_sent.shape[:2])} (B, N) agents, the state holds "
            f"{tuple(state.x.shape[:2])}"
        )
    return sensing
