"""``GraphCBFLearner``: one learner for GCBF, GCBF+, EGCBF and EGCBF+ (the group and the reference are parameters).

One update (GCBF+'s scheme):

1. roll out ``rollout_envs`` fresh episodes of ``rollout_steps`` steps with the current policy
   ``u = clip(u_nom + action_scale * pi(G))`` and label them (:func:`egcbf.algo.labels.finite_horizon_labels`);
2. draw ``memory_trajectories`` older trajectories and ``unsafe_samples`` unsafe graphs (with replacement) from
   the buffers, then add the new rollout to both buffers;
3. compute the reference control of every graph: ``u_nom`` (GCBF, EGCBF) or ``u_QP`` from the centralized QP
   with the *target* CBF (GCBF+, EGCBF+; :mod:`egcbf.algo.qp`);
4. ``epochs`` passes over the data in shuffled minibatches of ``batch_size`` graphs: the loss of
   :func:`egcbf.algo.loss.cbf_loss`, gradients of both networks, clipping to ``max_grad_norm`` per network, one
   AdamW step each;
5. soft update of the target CBF: ``phi_tgt <- tau phi + (1 - tau) phi_tgt``.

All randomness comes from the config's seed: network initialization from ``torch.manual_seed(seed)``, episode
resets from ``(seed, update)`` (:func:`rollout_seed`), buffer sampling and shuffling from ``self.generator``
(saved in checkpoints), so a run is reproducible and a resumed run continues exactly.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from collections import defaultdict

import torch
from torch import Tensor
from torch.func import functional_call

from ..env import EnvConfig, SwarmEnv, SwarmState
from ..env.graph import SwarmGraph, build_graph, refresh_graph
from ..nn import CBFNet, ModelConfig, PolicyNet, sensing
from ..robots import Robot
from .buffer import Samples, TrajectoryBuffer, UnsafeBuffer
from .config import TrainConfig
from .edge_qp import edge_qp_commands, edge_qp_controls
from .interface import CommandInterface, ControlInterface, make_interface, solve_command_qp
from .labels import finite_horizon_labels
from .loss import cbf_loss

__all__ = ["DTYPES", "GraphCBFLearner", "LearnedController", "rollout_seed"]

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def rollout_seed(seed: int, update: int) -> int:
    """The reset seed of the rollout of update ``update`` (a pure function: resuming needs no RNG state)."""
    return (int(seed) * 7_919_317 + 104_729 * (int(update) + 1)) % (2**62)


class LearnedController:
    """A trained policy as an evaluation controller: ``u, info = ctrl(state, env_config)``.

    Builds the graph of ``state`` (casting LiDAR), runs the policy and returns the applied body control: the
    command ``clip(c_nom + scale * pi)`` of the model's interface turned into torque and thrust (for ``"accel"``
    by the attitude loop). ``info["u_ref"]`` is the nominal controller's control (for the reward); for ``"accel"``,
    ``info["accel_command"]`` ``(B, N, 3)`` is the world acceleration command (m/s^2) that ``u`` tracks. No QP,
    barrier or other controller is involved.
    """

    name = "learned"
    #: builds its graph from the observed state, so message and LiDAR faults reach it (:mod:`egcbf.faults`)
    reads_sensing = True

    def __init__(self, policy: PolicyNet, model_config: ModelConfig):
        self.policy = policy
        self.model_config = model_config

    @torch.no_grad()
    def __call__(self, state: SwarmState, env_config: EnvConfig) -> tuple[Tensor, dict]:
        t0 = time.perf_counter()
        p = next(self.policy.parameters())
        s = state if state.x.dtype == p.dtype and state.x.device == p.device else state.to(p.device, dtype=p.dtype)
        graph = build_graph(s, env_config)
        u, u_nom, accel = act(self.policy, self.model_config, graph, s, env_config.make_robot())
        u = u.to(state.x.dtype).to(state.x.device)
        info = {"u_ref": u_nom.to(u), "num_slack": 0, "num_failed": 0, "ctrl_ms": 1e3 * (time.perf_counter() - t0)}
        if accel is not None:  # what a setpoint-flying low level tracks instead of u (egcbf eval --low-level)
            info["accel_command"] = accel.to(u)
        return u, info


def policy_command(
    policy: PolicyNet, model_config: ModelConfig, itf: CommandInterface, graph: SwarmGraph, x: Tensor, goals: Tensor
) -> tuple[Tensor, Tensor]:
    """The policy's command ``clip(c_nom + scale * pi)`` ``(B, N, k)`` and the nominal command ``c_nom``."""
    raw, c_nom = raw_policy_command(policy, model_config, itf, graph, x, goals)
    return itf.clip(x, raw), c_nom


def straight_through(raw: Tensor, clipped: Tensor) -> Tensor:
    """``clipped``'s value with ``raw``'s gradient (the identity): a straight-through clip."""
    return raw + (clipped - raw).detach()


def base_command(
    model_config: ModelConfig, itf: CommandInterface, x: Tensor, goals: Tensor, graph: SwarmGraph | None = None
) -> Tensor:
    """The command ``(B, N, k)`` of the law the policy acts around and the teacher aims at
    (``model_config.base_law``): the nominal controller's, the robot's brisk law (control interface; moved only
    ``model_config.brisk_weight`` of the way from the nominal law), or, for
    ``"brisk_isolated"``, the brisk law where an agent senses nothing in ``graph`` (the graph of ``x``; needed
    then) and the nominal law elsewhere."""
    law, w = model_config.base_law, model_config.brisk_weight
    if law == "nominal":
        return itf.nominal(x, goals)
    if law == "brisk_isolated" and graph is None:
        raise ValueError("base_law 'brisk_isolated' needs the agents' graph (what each agent senses)")
    brisk = itf.brisk(x, goals)
    if law == "brisk" and w == 1.0:
        return brisk
    nominal = itf.nominal(x, goals)
    if w != 1.0:
        brisk = nominal + w * (brisk - nominal)
    if law == "brisk":
        return brisk
    sensed = sensing(graph).view(*x.shape[:2], 1)
    return torch.where(sensed, nominal, brisk)


def needs_graph(model_config: ModelConfig) -> bool:
    """Whether :func:`base_command` reads the graph (the base law switches on what an agent senses)."""
    return model_config.base_law == "brisk_isolated"


def raw_policy_command(
    policy: PolicyNet, model_config: ModelConfig, itf: CommandInterface, graph: SwarmGraph, x: Tensor, goals: Tensor
) -> tuple[Tensor, Tensor]:
    """The policy's command before the clip, ``c_nom + scale * pi`` ``(B, N, k)``, and ``c_nom``, the base law's
    command (:func:`base_command`)."""
    b, n, _ = x.shape
    residual = policy(graph).view(b, n, itf.dim)
    c_nom = base_command(model_config, itf, x, goals, graph).to(residual.dtype)
    scales = torch.as_tensor(model_config.action_scales, dtype=residual.dtype, device=residual.device)
    return c_nom + scales * residual, c_nom


def act(
    policy: PolicyNet, model_config: ModelConfig, graph: SwarmGraph, state: SwarmState, robot: Robot
) -> tuple[Tensor, Tensor, Tensor | None]:
    """The policy's control ``(B, N, control_dim)`` in physical units (quadrotor: body torque and thrust), the
    nominal controller's control, and the world acceleration command ``(B, N, 3)`` (m/s^2) the control tracks, or
    ``None`` for an interface without one (:meth:`~.interface.CommandInterface.acceleration`)."""
    itf = make_interface(model_config.interface, robot)
    c, _ = policy_command(policy, model_config, itf, graph, state.x, state.goals)
    return itf.apply(state.x, c), robot.nominal_control(state.x, state.goals), itf.acceleration(c)


class GraphCBFLearner:
    """Networks, target CBF, optimizers, buffers and the update of one method (module doc).

    ``GraphCBFLearner(TrainConfig.preset("egcbf+", "cpu"))``; ``info = learner.update()`` once per training step;
    ``learner.controller()`` for evaluation; ``state_dicts()`` / ``load_state_dicts()`` for checkpoints.
    """

    def __init__(self, config: TrainConfig, device: str | torch.device | None = None, dtype: torch.dtype | None = None):
        self.config = config
        self.device = torch.device(device if device is not None else config.device)
        self.dtype = dtype or DTYPES[config.dtype]
        self.env_config = config.env_config()
        self.params = self.env_config.params
        self.robot = self.env_config.make_robot()
        self.interface = make_interface(config.model.interface, self.robot, **config.interface_options())
        torch.manual_seed(config.seed)
        self.cbf = CBFNet(config.model).to(self.device, self.dtype)
        self.policy = PolicyNet(config.model).to(self.device, self.dtype)
        self.cbf_target = copy.deepcopy(self.cbf).requires_grad_(False)
        self.opt_cbf = torch.optim.AdamW(self.cbf.parameters(), lr=config.lr_cbf, weight_decay=config.weight_decay)
        self.opt_policy = torch.optim.AdamW(
            self.policy.parameters(), lr=config.lr_policy, weight_decay=config.weight_decay
        )
        self.buffer = TrajectoryBuffer(config.buffer_trajectories)
        self.unsafe_buffer = UnsafeBuffer(config.unsafe_buffer_size)
        self.generator = torch.Generator().manual_seed(config.seed + 1)
        self.step = 0

    # ------------------------------------------------------------------------------------------------ acting
    def controller(self) -> LearnedController:
        return LearnedController(self.policy, self.config.model)

    @torch.no_grad()
    def collect(self, seed: int) -> Samples:
        """Roll out ``rollout_envs`` episodes of ``rollout_steps`` steps from ``reset(seed)`` with the current
        policy; returns labelled samples ``(B, L, ...)`` (one row per trajectory)."""
        cfg = self.env_config
        if self.config.area_sizes:
            cfg = dataclasses.replace(cfg, area_size=self.config.area_of_update(self.step))
        env = SwarmEnv(cfg, device=self.device, dtype=self.dtype)
        state = env.reset(seed)
        unsafe = env.info(state).unsafe
        xs, pts, valid, uns = [], [], [], []
        for _ in range(self.config.rollout_steps):
            scan = env.lidar(state)
            graph = build_graph(state, cfg, lidar=scan)
            xs.append(state.x)
            pts.append(scan.points)
            valid.append(scan.valid)
            uns.append(unsafe | env.approach_unsafe(state, scan))
            u, _, _ = act(self.policy, self.config.model, graph, state, self.robot)
            state, info = env.step(state, u)
            unsafe = info.unsafe
        unsafe_t = torch.stack(uns)  # (L, B, N)
        safe_t, unsafe_t = finite_horizon_labels(unsafe_t, self.config.horizon, self.config.truncated_safe)
        length = len(xs)

        def per_traj(t: Tensor) -> Tensor:  # (B, ...) -> (B, L, ...)
            return t[:, None].expand(t.shape[0], length, *t.shape[1:]).contiguous()

        return Samples(
            x=torch.stack(xs, 1),
            goals=per_traj(state.goals),
            centers=per_traj(state.obstacles.centers),
            radii=per_traj(state.obstacles.radii),
            boxes=per_traj(state.obstacles.packed_boxes),
            hit_points=torch.stack(pts, 1),
            hit_valid=torch.stack(valid, 1),
            safe=safe_t.transpose(0, 1).contiguous(),
            unsafe=unsafe_t.transpose(0, 1).contiguous(),
        )

    # --------------------------------------------------------------------------------------------- targets
    @torch.no_grad()
    def reference(self, data: Samples) -> tuple[Tensor, dict]:
        """The reference command ``(S, N, k)`` of every sample (world-frame, normalized), and QP statistics (empty
        for the nominal reference)."""
        cfg, itf, env_cfg = self.config, self.interface, self.env_config
        chunks = [data[k : k + cfg.qp_chunk] for k in range(0, len(data), cfg.qp_chunk)]
        # a base law that reads what agents sense needs every chunk's graph first; the QPs then reuse them
        graphs = [chunk.graph(env_cfg) for chunk in chunks] if needs_graph(cfg.model) else None

        def graph_of(i: int) -> SwarmGraph:
            return graphs[i] if graphs is not None else chunks[i].graph(env_cfg)

        if graphs is not None:
            c_noms = [base_command(cfg.model, itf, c.x, c.goals, g) for c, g in zip(chunks, graphs, strict=True)]
        else:
            c_noms = list(torch.split(base_command(cfg.model, itf, data.x, data.goals), cfg.qp_chunk))
        if cfg.reference == "nominal":
            return torch.cat(c_noms), {}
        if cfg.qp_constraints == "edges":
            return self._edge_reference(chunks, graph_of, c_noms)
        out, stats = [], defaultdict(float)
        t0 = time.perf_counter()
        for i, (chunk, c_nom) in enumerate(zip(chunks, c_noms, strict=True)):
            c_qp, res = solve_command_qp(
                itf, self.cbf_target, graph_of(i), chunk.x, c_nom, env_cfg, alpha=cfg.qp_alpha,
                slack_linear=cfg.qp_slack_linear, slack_quadratic=cfg.qp_slack_quadratic, tol=cfg.qp_tol,
                max_iter=cfg.qp_max_iter, chunk=cfg.qp_chunk,
            )  # fmt: skip
            out.append(c_qp.to(self.dtype))
            s = res.stats()
            for key in ("num_slack", "num_failed", "num_constraints"):
                stats[key] += s[key]
            stats["max_slack"] = max(stats["max_slack"], s["max_slack"])
            stats["iterations"] = max(stats["iterations"], res.iterations)
        stats["ms"] = 1e3 * (time.perf_counter() - t0)
        return torch.cat(out), dict(stats)

    def _edge_reference(self, chunks: list[Samples], graph_of, c_noms: list[Tensor]) -> tuple[Tensor, dict]:
        """``qp_constraints = "edges"``: every agent's per-edge QP with the target CBF's edge barriers around its
        nominal command (:mod:`egcbf.algo.edge_qp`), chunk by chunk (``graph_of(i)``: chunk ``i``'s graph)."""
        cfg, itf, mc = self.config, self.interface, self.config.model
        out, stats = [], defaultdict(float)
        t0 = time.perf_counter()
        barrier = dict(
            alpha=cfg.qp_edge_alpha, margin=0.0, cbf=self.cbf_target, distance=mc.cbf_distance,
            horizon=mc.closest_approach_horizon,
        )  # fmt: skip
        for i, (chunk, c_nom) in enumerate(zip(chunks, c_noms, strict=True)):
            if isinstance(itf, ControlInterface):
                c, info = edge_qp_controls(graph_of(i), chunk.x, itf, c_nom, min_authority=cfg.qp_edge_min_authority,
                                           **barrier)  # fmt: skip
                out.append(c.to(self.dtype))
            else:
                a, info = edge_qp_commands(graph_of(i), chunk.x, itf, itf.accel_unit * c_nom, **barrier)
                out.append((a / itf.accel_unit).to(self.dtype))
            for key in ("num_slack", "num_failed", "rows_dropped"):
                stats[key] += info[key]
            stats["max_slack"] = max(stats["max_slack"], info["max_slack"])
        stats["ms"] = 1e3 * (time.perf_counter() - t0)
        return torch.cat(out), dict(stats)

    # ------------------------------------------------------------------------------------------------ loss
    def loss(self, batch: Samples, u_ref: Tensor) -> dict[str, Tensor]:
        """The loss terms of a minibatch ``(S, ...)`` against its reference commands ``(S, N, k)``."""
        cfg, env_cfg, itf = self.config, self.env_config, self.interface
        graph = batch.graph(env_cfg)
        k = itf.dim
        h = self.cbf(graph)
        raw, _ = raw_policy_command(self.policy, cfg.model, itf, graph, batch.x, batch.goals)
        c = itf.clip(batch.x, raw)
        # straight through the clip: the command's value, the raw command's gradient, so that a policy pushing
        # beyond the box (at a speed limit: beyond 0) still learns from the reference's braking
        c_imitated = straight_through(raw, c) if cfg.straight_through_clip else c
        x_next = itf.model_step(batch.x, c, env_cfg)
        graph_next = refresh_graph(graph, x_next)
        # h(x') with the CBF's parameters for labelled agents and with them frozen for the others (cbf_loss): each
        # on the edges into its own agents only, so the two passes cost one
        labelled = (batch.safe | batch.unsafe).reshape(-1)
        if not cfg.hdot_trains_cbf:  # the derivative term trains the policy only
            labelled = torch.zeros_like(labelled)
        h_next = self.cbf(graph_next.with_receivers(labelled))
        frozen = {name: v.detach() for name, v in self.cbf.named_parameters()}
        h_next_frozen = functional_call(self.cbf, frozen, (graph_next.with_receivers(~labelled),))
        return cbf_loss(
            h, h_next, batch.safe.reshape(-1), batch.unsafe.reshape(-1), c_imitated.reshape(-1, k),
            u_ref.reshape(-1, k),
            env_cfg.dt, gamma=cfg.gamma, alpha=cfg.alpha, eta_d=cfg.eta_d, eta_c=cfg.eta_c, eta_safe=cfg.eta_safe,
            eta_unsafe=cfg.eta_unsafe, control=cfg.control_loss, h_next_frozen=h_next_frozen,
            hdot_labelled=labelled,
        )  # fmt: skip

    def train_step(self, batch: Samples, u_ref: Tensor) -> dict[str, float]:
        """One gradient step of both networks on a minibatch; returns the loss terms and gradient norms."""
        terms = self.loss(batch, u_ref)
        self.opt_cbf.zero_grad(set_to_none=True)
        self.opt_policy.zero_grad(set_to_none=True)
        terms["total"].backward()
        gn_cbf = torch.nn.utils.clip_grad_norm_(self.cbf.parameters(), self.config.max_grad_norm)
        gn_pol = torch.nn.utils.clip_grad_norm_(self.policy.parameters(), self.config.max_grad_norm)
        self.opt_cbf.step()
        self.opt_policy.step()
        out = {k: float(v.detach()) for k, v in terms.items()}
        out["grad_norm_cbf"], out["grad_norm_policy"] = float(gn_cbf), float(gn_pol)
        return out

    @torch.no_grad()
    def soft_update_target(self) -> None:
        tau = self.config.target_tau
        for pt, p in zip(self.cbf_target.parameters(), self.cbf.parameters()):
            pt.lerp_(p, tau)

    # ---------------------------------------------------------------------------------------------- update
    def assemble(self, rollout: Samples) -> Samples:
        """Step 2 of the update: the training data of this update (and the rollout stored in the buffers)."""
        cfg = self.config
        memory = self.buffer.sample(cfg.memory_trajectories, self.generator)
        unsafe = self.unsafe_buffer.sample(cfg.unsafe_samples, self.generator)
        self.buffer.append(rollout)
        flat = rollout.flatten()
        self.unsafe_buffer.add(flat)
        data = Samples.cat([flat, None if memory is None else memory.flatten()])
        if cfg.train_graphs is not None and cfg.train_graphs < len(data):
            data = data[torch.randperm(len(data), generator=self.generator)[: cfg.train_graphs].to(data.x.device)]
        return Samples.cat([data, unsafe])

    def fit(self, data: Samples, u_ref: Tensor, epochs: int | None = None) -> dict[str, float]:
        """Step 4: ``epochs`` shuffled passes in minibatches; returns the mean of each term over the last epoch."""
        cfg = self.config
        n = len(data)
        last: dict[str, list[float]] = defaultdict(list)
        for _ in range(cfg.epochs if epochs is None else epochs):
            last.clear()
            perm = torch.randperm(n, generator=self.generator).to(data.x.device)
            for idx in torch.tensor_split(perm, max(1, n // cfg.batch_size)):
                for k, v in self.train_step(data[idx], u_ref[idx]).items():
                    last[k].append(v)
        return {k: sum(v) / len(v) for k, v in last.items()}

    def update(self) -> dict[str, float]:
        """One training update (module doc); returns losses, label counts, QP statistics and timings."""
        t0 = time.perf_counter()
        rollout = self.collect(rollout_seed(self.config.seed, self.step))
        t1 = time.perf_counter()
        data = self.assemble(rollout)
        u_ref, qp = self.reference(data)
        t2 = time.perf_counter()
        info = {f"loss/{k}": v for k, v in self.fit(data, u_ref).items()}
        self.soft_update_target()
        self.step += 1
        t3 = time.perf_counter()
        labelled = data.safe | data.unsafe
        info.update(
            {
                "data/graphs": float(len(data)),
                "data/safe": float(data.safe.sum()),
                "data/unsafe": float(data.unsafe.sum()),
                "data/unlabelled": float((~labelled).sum()),
                "data/rollout_unsafe_frac": float(rollout.unsafe.any(1).float().mean()),
                "buffer/trajectories": float(len(self.buffer)),
                "buffer/unsafe": float(len(self.unsafe_buffer)),
                "time/rollout_s": t1 - t0,
                "time/reference_s": t2 - t1,
                "time/fit_s": t3 - t2,
                "time/update_s": t3 - t0,
            }
        )
        info.update({f"qp/{k}": float(v) for k, v in qp.items()})
        return info

    # ------------------------------------------------------------------------------------------ checkpoints
    def weights(self) -> dict[str, Tensor]:
        """All network weights, prefixed ``cbf.``, ``policy.``, ``cbf_target.`` (for safetensors)."""
        out = {}
        for prefix, net in (("cbf", self.cbf), ("policy", self.policy), ("cbf_target", self.cbf_target)):
            out.update({f"{prefix}.{k}": v.detach().contiguous() for k, v in net.state_dict().items()})
        return out

    def load_weights(self, weights: dict[str, Tensor]) -> None:
        for prefix, net in (("cbf", self.cbf), ("policy", self.policy), ("cbf_target", self.cbf_target)):
            sd = {k[len(prefix) + 1 :]: v for k, v in weights.items() if k.startswith(prefix + ".")}
            net.load_state_dict(sd)

    def training_state(self) -> dict:
        """Optimizer states and the sampling generator's state (for ``torch.save``; loads with weights_only)."""
        return {
            "opt_cbf": self.opt_cbf.state_dict(),
            "opt_policy": self.opt_policy.state_dict(),
            "generator": self.generator.get_state(),
            "step": self.step,
        }

    def load_training_state(self, state: dict) -> None:
        self.opt_cbf.load_state_dict(state["opt_cbf"])
        self.opt_policy.load_state_dict(state["opt_policy"])
        self.generator.set_state(state["generator"])
        self.step = int(state["step"])

    def buffers(self) -> dict[str, Tensor]:
        return {**self.buffer.state_dict(), **self.unsafe_buffer.state_dict()}

    def load_buffers(self, sd: dict[str, Tensor]) -> None:
        self.buffer.load_state_dict(sd)
        self.unsafe_buffer.load_state_dict(sd)
        for buf in (self.buffer, self.unsafe_buffer):
            if buf.data is not None:
                buf.data = buf.data.to(self.device)
