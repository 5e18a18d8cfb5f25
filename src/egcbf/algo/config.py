"""Typed training configuration: one dataclass, six presets (``cpu``, ``paper-cpu``, ``paper-cpu-mlp``,
``cpu-torque``, ``paper``, ``tiny``), JSON round trip.

    cfg = TrainConfig.preset("egcbf+", "cpu")          # or "paper-cpu", "paper-cpu-mlp", "cpu-torque", "paper", "tiny"
    cfg = TrainConfig.from_json(path)                   # what every checkpoint stores beside its weights

The four methods are points of one grid (``LEARNED_METHODS``): the symmetry group of the networks times the reference
controller of the control loss::

    gcbf   = (trivial,     nominal)    gcbf+  = (trivial,     qp)
    egcbf  = (equivariant, nominal)    egcbf+ = (equivariant, qp)

``algo`` names the point; ``model.group`` (``"trivial"`` or the robot's own group: ``"se2xr"`` for the quadrotor,
``"se2"`` for the planar unicycle) and ``reference`` are set from it (and checked against it when a config file gives
them). The robot is ``model.robot`` (:mod:`egcbf.robots`); the training environment is built for it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from ..env import EnvConfig
from ..nn.models import ModelConfig
from ..robots import DEFAULT_ROBOT, make_robot
from .presets import GCBFPLUS_TRAINING, LEARNED_METHODS, PRESETS, method_group, preset_fields

__all__ = ["GCBFPLUS_TRAINING", "LEARNED_METHODS", "PRESETS", "TrainConfig", "method_group"]


@dataclass
class TrainConfig:
    """Everything a training run needs; saved as JSON beside every checkpoint.

    Method: ``algo`` (one of :data:`LEARNED_METHODS`), ``reference`` (``"nominal"`` or ``"qp"``, set from ``algo``),
    ``model`` (:class:`egcbf.nn.ModelConfig`, its ``group`` set from ``algo`` and its ``robot``).

    Robot: ``model.robot`` (``robot`` is a read-only alias); the environment starts from that robot's defaults
    (:meth:`egcbf.env.EnvConfig.for_robot`).

    Training environment: ``num_agents``, ``area_size``, ``num_obstacles`` and ``env_overrides`` (any other
    :class:`egcbf.env.EnvConfig` field, e.g. ``{"comm_radius": 1.0}``); the episode length of the rollouts is
    ``rollout_steps``. ``area_sizes`` (a list, or ``None``): the rollout of update ``k`` uses
    ``area_sizes[k % len(area_sizes)]`` instead of ``area_size``, so that training covers several densities
    (the agent count, and so the shape of the replay buffers, stays ``num_agents``). ``scene``
    (:data:`egcbf.env.scenes.SCENES`): where the rollouts' and the validation's starts and goals are drawn
    (``"crossing"``: a training distribution with a preferred direction, for the rotated-world test); it is the
    run's own, never inherited by ``egcbf eval`` (which takes ``--scene``), so it is not an ``env_overrides`` key.

    Command model (``model.interface == "accel"`` only, :mod:`egcbf.algo.interface`): ``command_model``,
    ``"ideal"`` (the double integrator the acceleration command defines) or ``"closed_loop"`` (one step through the
    attitude loop and the rigid body), for the QP's ``Lg h`` and the loss's next state.

    Data (GCBF+): every update rolls out ``rollout_envs`` environments for ``rollout_steps`` steps with the
    current policy (fresh episodes), labels them with look-ahead ``horizon`` (``truncated_safe``: see
    :mod:`egcbf.algo.labels`), and trains on those graphs plus ``memory_trajectories`` trajectories drawn from the
    last ``buffer_trajectories`` ones plus ``unsafe_samples`` graphs drawn with replacement from the last
    ``unsafe_buffer_size`` graphs with an unsafe agent. ``train_graphs`` (``None``: all): of the rollout and memory
    graphs, only this many, drawn at random without replacement, are trained on (consecutive steps of a rollout
    are nearly the same graph; dense scenes make every graph expensive).

    Optimization: ``epochs`` passes over that data in minibatches of ``batch_size`` graphs; AdamW
    (``lr_cbf``, ``lr_policy``, ``weight_decay``), gradient norm clipped to ``max_grad_norm`` per network.

    Loss (:func:`egcbf.algo.loss.cbf_loss`): ``gamma``, ``alpha``, ``eta_d``, ``eta_c``, ``eta_safe``,
    ``eta_unsafe``, ``control_loss`` (``"squared"`` or ``"norm"``), ``straight_through_clip`` (the control
    term's gradient passes straight through the command's clip, so a policy beyond the box still learns; the
    ``gcbfplus`` recipe), ``hdot_trains_cbf`` (``False``: the derivative term trains the policy only, through the
    next state, with the CBF frozen for every agent).

    QP target (:mod:`egcbf.algo.qp`): ``qp_alpha`` (the constraint's class-K slope; GCBF+ uses 0.1 alpha),
    ``qp_slack_linear``/``qp_slack_quadratic`` (slack cost ``w1 s + w2 s^2 / 2``), ``qp_tol``, ``qp_max_iter``,
    ``qp_chunk`` (environments per batched solve), ``target_tau`` (soft update of the target CBF after each update).
    ``qp_constraints``: ``"cbf"`` (the paper's and GCBF+'s: one centralized QP per scene, one condition per agent on
    its ``h_i``) or ``"edges"`` (one QP per agent over its own command, one condition per barrier of an edge it
    senses, pair conditions halved: :mod:`egcbf.algo.edge_qp`; needs the soft-min CBF head, and the acceleration
    interface or the control interface of a robot whose state holds its velocity), with the class-K gain
    ``qp_edge_alpha`` (1/s, per-edge barriers in m); for the control interface, rows that a unit of normalized control
    moves by no more than ``qp_edge_min_authority`` (m/s) are dropped (:func:`egcbf.algo.edge_qp.edge_qp_controls`).

    Run: ``steps`` (updates), ``max_wall_minutes`` (stop earlier, after the first update that ends past this much
    training wall time, with a final evaluation and checkpoint; ``None``: no limit), ``max_cpu_minutes`` (the same
    on the training process's CPU time, all its threads: a budget that other jobs on the machine do not eat into,
    for comparisons run beside other work; ``None``: no limit), ``seed``, ``device``,
    ``dtype``, ``deterministic``
    (``torch.use_deterministic_algorithms``), ``num_threads`` (0: leave torch's default), ``eval_interval``,
    ``eval_episodes``, ``eval_num_agents``, ``eval_area_size``, ``eval_num_obstacles``, ``eval_max_steps``
    (periodic evaluation rollouts; ``eval_*=None``: the training values, 256-step episodes),
    ``checkpoint_interval``, ``keep_checkpoints`` (0: keep all), ``save_buffers`` (store the replay buffers in
    checkpoints so that ``--resume`` continues bit for bit).

    Warm start (fine-tuning): ``init_from`` (a checkpoint or run directory; a run's ``best/``) gives the networks'
    starting weights (CBF, its target copy and policy; fresh optimizers, buffers and update count), and
    ``init_sha256`` the SHA-256 of its ``model.safetensors``: recorded by :func:`egcbf.train.loop.train` when ``None``,
    checked when given, so a config beside a checkpoint says exactly which weights the run started from.
    """

    algo: str = "egcbf+"
    reference: str = "qp"
    model: ModelConfig = field(default_factory=ModelConfig)
    # training environment
    num_agents: int = 8
    area_size: float = 2.0
    num_obstacles: int = 5
    area_sizes: list[float] | None = None
    env_overrides: dict[str, Any] = field(default_factory=dict)
    scene: str = "uniform"
    command_model: str = "ideal"
    # data
    rollout_envs: int = 4
    rollout_steps: int = 128
    horizon: int = 32
    truncated_safe: bool = True
    buffer_trajectories: int = 64
    memory_trajectories: int = 4
    unsafe_buffer_size: int = 256
    unsafe_samples: int = 256
    train_graphs: int | None = None
    # optimization
    epochs: int = 2
    batch_size: int = 128
    lr_cbf: float = 1e-4
    lr_policy: float = 1e-5
    weight_decay: float = 1e-3
    max_grad_norm: float = 2.0
    # loss
    gamma: float = 0.02
    alpha: float = 1.0
    eta_d: float = 0.2
    eta_c: float = 1.0
    eta_safe: float = 1.0
    eta_unsafe: float = 1.0
    control_loss: str = "squared"
    straight_through_clip: bool = False
    hdot_trains_cbf: bool = True
    # QP target
    qp_alpha: float = 0.1
    qp_slack_linear: float = 1e3
    qp_slack_quadratic: float = 10.0
    qp_tol: float = 1e-8
    qp_max_iter: int = 50
    qp_chunk: int = 1024
    qp_constraints: str = "cbf"
    qp_edge_alpha: float = 1.0
    qp_edge_min_authority: float = 1e-9
    target_tau: float = 0.5
    # run
    steps: int = 1000
    max_wall_minutes: float | None = None
    max_cpu_minutes: float | None = None
    seed: int = 0
    device: str = "cpu"
    dtype: str = "float32"
    deterministic: bool = True
    num_threads: int = 0
    eval_interval: int = 10
    eval_episodes: int = 8
    eval_num_agents: int | None = None
    eval_area_size: float | None = None
    eval_num_obstacles: int | None = None
    eval_max_steps: int | None = None
    checkpoint_interval: int = 25
    keep_checkpoints: int = 3
    save_buffers: bool = True
    init_from: str | None = None
    init_sha256: str | None = None

    def __post_init__(self) -> None:
        if isinstance(self.model, dict):
            self.model = ModelConfig(**self.model)
        if self.algo not in LEARNED_METHODS:
            raise ValueError(f"TrainConfig.algo must be one of {sorted(LEARNED_METHODS)}, got {self.algo!r}")
        _, reference = LEARNED_METHODS[self.algo]
        group = method_group(self.algo, self.model.robot)
        if self.reference != reference or self.model.group != group:
            raise ValueError(
                f"TrainConfig: algo {self.algo!r} means group={group!r}, reference={reference!r}, but the config "
                f"has group={self.model.group!r}, reference={self.reference!r}"
            )

        def need(ok: bool, name: str, what: str) -> None:
            if not ok:
                raise ValueError(f"TrainConfig.{name} must be {what}, got {getattr(self, name)!r}")

        scene_keys = sorted({"scene", "scene_yaw"} & set(self.env_overrides or {}))
        need(not scene_keys, "env_overrides", f"free of {scene_keys} (set TrainConfig.scene; evaluation takes "
             "--scene and --scene-yaw)")  # fmt: skip
        # the run's own sizes and lengths: training replaces them, and evaluation must not inherit them
        run_keys = sorted({"num_agents", "num_envs", "area_size", "num_obstacles", "max_steps"}
                          & set(self.env_overrides or {}))  # fmt: skip
        need(not run_keys, "env_overrides", f"free of {run_keys} (set TrainConfig.num_agents, area_size, "
             "num_obstacles and rollout_steps; evaluation takes --num-agents, --area, --obstacles, "
             "--max-steps)")  # fmt: skip

        for name in ("rollout_envs", "rollout_steps", "buffer_trajectories", "unsafe_buffer_size", "epochs",
                     "batch_size", "steps", "eval_interval", "eval_episodes", "checkpoint_interval", "qp_max_iter",
                     "qp_chunk"):  # fmt: skip
            v = getattr(self, name)
            need(isinstance(v, int) and not isinstance(v, bool) and v >= 1, name, "an integer >= 1")
        if self.train_graphs is not None:
            need(isinstance(self.train_graphs, int) and self.train_graphs >= 1, "train_graphs", "None or an int >= 1")
        for name in ("horizon", "memory_trajectories", "unsafe_samples", "keep_checkpoints", "num_threads"):
            v = getattr(self, name)
            need(isinstance(v, int) and not isinstance(v, bool) and v >= 0, name, "an integer >= 0")
        for name in ("lr_cbf", "lr_policy", "max_grad_norm", "qp_tol", "qp_slack_quadratic"):
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and math.isfinite(v) and v > 0, name, "a finite number > 0")
        for name in ("weight_decay", "gamma", "alpha", "eta_d", "eta_c", "eta_safe", "eta_unsafe", "qp_alpha",
                     "qp_slack_linear"):  # fmt: skip
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and math.isfinite(v) and v >= 0, name, "a finite number >= 0")
        need(0 <= self.target_tau <= 1, "target_tau", "in [0, 1]")
        for name in ("max_wall_minutes", "max_cpu_minutes"):
            v = getattr(self, name)
            ok = v is None or (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0)
            need(ok, name, "None or > 0")
        need(self.control_loss in ("squared", "norm"), "control_loss", "'squared' or 'norm'")
        need(self.init_from is None or (isinstance(self.init_from, str) and self.init_from.strip() != ""),
             "init_from", "None or a checkpoint path")  # fmt: skip
        sha = self.init_sha256
        need(sha is None or (isinstance(sha, str) and re.fullmatch(r"[0-9a-f]{64}", sha) is not None),
             "init_sha256", "None or a hex SHA-256")  # fmt: skip
        need(self.command_model in ("ideal", "closed_loop"), "command_model", "'ideal' or 'closed_loop'")
        need(self.qp_constraints in ("cbf", "edges"), "qp_constraints", "'cbf' or 'edges'")
        v = self.qp_edge_alpha
        need(isinstance(v, (int, float)) and math.isfinite(v) and v > 0, "qp_edge_alpha", "a finite number > 0")
        v = self.qp_edge_min_authority
        need(isinstance(v, (int, float)) and math.isfinite(v) and v >= 0, "qp_edge_min_authority",
             "a finite number >= 0")  # fmt: skip
        if self.qp_constraints == "edges":
            m = self.model
            ok = m.interface in ("accel", "control") and m.cbf_head == "edge_min" and not m.cbf_z_symmetric
            if m.interface == "control":
                ok = ok and not make_robot(m.robot).kinematic
            need(ok, "qp_constraints", "'cbf' unless the model has the acceleration or (for a robot whose state holds "
                 "its velocity) the control interface and the soft-min CBF head (cbf_head = 'edge_min', "
                 "cbf_z_symmetric = False)")  # fmt: skip
        if self.area_sizes is not None:
            ok = isinstance(self.area_sizes, (list, tuple)) and len(self.area_sizes) > 0
            ok = ok and all(isinstance(a, (int, float)) and math.isfinite(a) and a > 0 for a in self.area_sizes)
            need(ok, "area_sizes", "None or a non-empty list of numbers > 0")
            self.area_sizes = [float(a) for a in self.area_sizes]
        need(self.dtype in ("float32", "float64"), "dtype", "'float32' or 'float64'")
        need(isinstance(self.seed, int) and not isinstance(self.seed, bool) and self.seed >= 0, "seed",
             "an integer >= 0")  # fmt: skip
        for name in ("eval_num_agents", "eval_num_obstacles", "eval_max_steps"):
            v = getattr(self, name)
            need(v is None or (isinstance(v, int) and not isinstance(v, bool)), name, "None or an integer")
        # the training and evaluation environments are built now, not at the first rollout or evaluation
        for what, fields, build in (
            ("training", "num_agents, area_size(s), num_obstacles, scene, env_overrides", self._every_training_env),
            ("evaluation", "eval_num_agents, eval_area_size, eval_num_obstacles, eval_max_steps", self.eval_env_config),
        ):
            try:
                build()
            except (TypeError, ValueError) as err:
                raise ValueError(f"TrainConfig: the {what} environment ({fields}) is invalid: {err}") from None

    def _every_training_env(self) -> None:
        for area in self.area_sizes or [self.area_size]:
            self.env_config(area_size=area)

    # ------------------------------------------------------------------------------------------- derived
    @property
    def group(self) -> str:
        return self.model.group

    @property
    def robot(self) -> str:
        return self.model.robot

    def interface_options(self) -> dict[str, Any]:
        """Keyword arguments of :func:`egcbf.algo.interface.make_interface` beyond the interface's name."""
        return {"model": self.command_model} if self.model.interface == "accel" else {}

    def area_of_update(self, update: int) -> float:
        """The arena side of update ``update``'s rollout (``area_sizes`` cycled, else ``area_size``)."""
        return self.area_size if not self.area_sizes else self.area_sizes[update % len(self.area_sizes)]

    def env_config(self, **changes) -> EnvConfig:
        """The training environment's :class:`EnvConfig` (``num_envs = rollout_envs``), with ``changes``."""
        kw = dict(self.env_overrides)
        kw.update(
            scene=self.scene,
            num_agents=self.num_agents,
            area_size=self.area_size,
            num_obstacles=self.num_obstacles,
            num_envs=self.rollout_envs,
            max_steps=self.rollout_steps,
        )
        kw.update(changes)
        return EnvConfig.for_robot(self.model.robot, **kw)

    def eval_env_config(self) -> EnvConfig:
        """The evaluation environment (training values where the ``eval_*`` fields are ``None``)."""
        ch = {"num_envs": self.eval_episodes}
        for f, key in (("eval_num_agents", "num_agents"), ("eval_area_size", "area_size"),
                       ("eval_num_obstacles", "num_obstacles")):  # fmt: skip
            if getattr(self, f) is not None:
                ch[key] = getattr(self, f)
        default_steps = EnvConfig.for_robot(self.model.robot).max_steps
        ch["max_steps"] = self.eval_max_steps if self.eval_max_steps is not None else default_steps
        return self.env_config(**ch)

    # ------------------------------------------------------------------------------------------- presets
    @classmethod
    def preset(cls, algo: str, name: str = "cpu", robot: str = DEFAULT_ROBOT, **changes) -> TrainConfig:
        """The config of method ``algo`` under preset ``name`` for ``robot`` (the recipes:
        :func:`egcbf.algo.presets.preset_fields`). ``changes`` override fields (``model`` may be a dict of
        :class:`ModelConfig` overrides)."""
        model, base = preset_fields(algo, name, robot)
        model.update(changes.pop("model", {}) or {})
        base.update(changes)
        return cls(algo=algo, reference=LEARNED_METHODS[algo][1], model=ModelConfig(**model), **base)

    # ------------------------------------------------------------------------------------------- JSON
    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        d = dict(d)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown TrainConfig fields: {unknown}")
        if isinstance(d.get("model"), dict):
            d["model"] = ModelConfig(**d["model"])
        return cls(**d)

    def to_json(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def from_json(cls, path: str | Path) -> TrainConfig:
        return cls.from_dict(json.loads(Path(path).read_text()))

    def replace(self, **changes) -> TrainConfig:
        return dataclasses.replace(self, **changes)
