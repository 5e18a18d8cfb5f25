"""The one place that builds a controller from its name and, for a learned one, its checkpoint.

A controller's name is ``METHOD[:FILTER]`` (:mod:`egcbf.control.names`): ``METHOD`` a hand-crafted controller of
the robot (``"nominal"``, ``"brisk"``, ``"dcbf"``, ``"ccbf"``: :func:`~egcbf.control.controllers.make_controller`)
or, with a checkpoint, the checkpoint's method (``"egcbf+"``, or a MARL baseline's ``"ippo-lag"``:
:mod:`egcbf.marl`; ``"policy"`` stands for whichever method the checkpoint holds); ``FILTER`` a run-time safety
filter (:mod:`egcbf.control.filters`) around the method's command::

    built = resolve("egcbf+:dcbf", "checkpoints/egcbf+")      # EGCBF+'s policy behind the dcbf filter
    built = resolve("policy", "runs/my-run")                    # a run's best/ policy, whatever its method
    built = resolve("nominal:dcbf")                             # the nominal command behind the filter
    built = resolve("dcbf", robot="double_integrator")          # the robot's own dCBF-QP
    u, info = built.controller(state, env_config)

A checkpoint's files are read once per controller built (:func:`egcbf.train.checkpoint.read_checkpoint`): its
policy, and for the ``cbf`` filter its CBF, come from the same read. Bad names, a checkpoint that does not hold
``METHOD``, or a robot that is not the checkpoint's raise :class:`ControllerError` (a ``ValueError``) saying why;
unreadable checkpoints raise :class:`~egcbf.train.checkpoint.CheckpointError` or ``FileNotFoundError``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ..robots import DEFAULT_ROBOT, ROBOTS
from .controllers import make_controller, robot_controllers
from .names import join_method, split_method

__all__ = ["POLICY", "ControllerError", "ResolvedController", "reads_sensing", "resolve"]

#: the method name that stands for a checkpoint's own method
POLICY = "policy"


class ControllerError(ValueError):
    """A controller name, checkpoint and robot that do not make a controller (the message says why)."""


@dataclass(frozen=True)
class ResolvedController:
    """A built controller and what it was built from.

    Attributes:
        name: ``METHOD[:FILTER]`` with ``METHOD`` the checkpoint's method for a learned one (``"egcbf+:dcbf"``).
        controller: ``u, info = controller(state, env_config)`` (:mod:`egcbf.control.controllers`).
        robot: the robot it drives (a checkpoint's own).
        filter: the run-time filter's kind, ``"none"`` without one.
        checkpoint: the checkpoint directory read (of a run: its ``best/`` or newest checkpoint), or ``None``.
        weights_sha256: the SHA-256 of that checkpoint's ``model.safetensors``, or ``None``.
        train_config: the checkpoint's ``TrainConfig``, or ``None``.
        cbf: the checkpoint's learned CBF (an :class:`egcbf.nn.models.CBFNet`) where the controller uses it (the
            ``cbf`` filter) or it was asked for (``resolve(..., with_cbf=True)``), else ``None``.
    """

    name: str
    controller: Any
    robot: str
    filter: str = "none"
    checkpoint: Path | None = None
    weights_sha256: str | None = None
    train_config: Any = None
    cbf: Any = None

    @property
    def env_overrides(self) -> dict | None:
        """The environment settings a learned policy was trained with (sensing radii, LiDAR), else ``None``."""
        return None if self.train_config is None else dict(self.train_config.env_overrides)

    @property
    def reads_sensing(self):
        """What the controller perceives (:func:`egcbf.faults.sensing.unread_faults`): ``True`` (everything), a set
        of channel names, or ``False`` (the true state only)."""
        return getattr(self.controller, "reads_sensing", False)


def reads_sensing(name: str, robot: str = DEFAULT_ROBOT):
    """What the controller named ``name`` perceives, without building it: ``True`` for a learned policy, alone or
    filtered (its graph is built from what the agents perceive); the filter rows' channels for a filtered
    hand-crafted command; a hand-crafted controller's own declaration (``reads_sensing``, default ``False``)."""
    from .filters import filter_reads_sensing

    method, kind = split_method(name)
    hand_crafted = robot_controllers(robot)
    if kind != "none":
        return filter_reads_sensing(kind, has_policy=method not in hand_crafted)
    if method in hand_crafted:
        return getattr(hand_crafted[method], "reads_sensing", False)
    return True


def resolve(
    name: str,
    checkpoint: str | Path | None = None,
    *,
    robot: str | None = None,
    filter_config=None,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    with_cbf: bool = False,
    **options,
) -> ResolvedController:
    """Build the controller ``name`` (``METHOD[:FILTER]``, module doc).

    Args:
        name: the controller's name; with ``checkpoint``, ``METHOD`` is the checkpoint's method or ``"policy"``.
        checkpoint: a checkpoint or run directory of a learned policy, or ``None`` for a hand-crafted controller.
        robot: the robot (default: the checkpoint's, else :data:`egcbf.robots.DEFAULT_ROBOT`); a checkpoint's robot
            must match.
        filter_config: the filter's settings (:class:`~egcbf.control.filters.FilterConfig`; default its
            ``for_kind(FILTER)``); its ``kind`` must be ``FILTER``.
        device, dtype: where a learned policy's networks live.
        with_cbf: also build the checkpoint's learned CBF (``ResolvedController.cbf``, e.g. to record its values
            along an episode) from the same read of the checkpoint; without a graph policy's checkpoint it stays
            ``None``.
        **options: keyword arguments of a hand-crafted controller (:func:`~egcbf.control.controllers.make_controller`).

    Returns:
        The :class:`ResolvedController`.
    """
    from .filters import FilterConfig, FilteredController

    try:
        method, kind = split_method(name)
    except ValueError as err:
        raise ControllerError(str(err)) from None
    if filter_config is None and kind != "none":
        filter_config = FilterConfig.for_kind(kind)
    if filter_config is not None and filter_config.kind != kind:
        raise ControllerError(f"{name}: the filter settings are of {filter_config.kind!r}, the name says {kind!r}")
    if checkpoint is None:
        return _hand_crafted(name, method, kind, robot or DEFAULT_ROBOT, filter_config, options)
    if options:
        raise ControllerError(f"{name}: {sorted(options)} set a hand-crafted controller, not a checkpoint's policy")
    from ..marl.checkpoint import is_marl_checkpoint

    if is_marl_checkpoint(checkpoint):
        return _marl(name, method, kind, Path(checkpoint), robot, device, dtype)
    from ..algo.learner import LearnedController
    from ..train.checkpoint import build_network, read_checkpoint

    contents = read_checkpoint(checkpoint)
    cfg = contents.config
    if method not in (POLICY, cfg.algo):
        raise ControllerError(f"{name}: {contents.directory} holds a {cfg.algo} policy, not {method}")
    if robot not in (None, cfg.robot):
        raise ControllerError(f"robot {robot} but the checkpoint's policy drives a {cfg.robot}")
    policy = build_network(contents, "policy", device, dtype)
    cbf = build_network(contents, "cbf", device, dtype) if kind == "cbf" or with_cbf else None
    if filter_config is None:
        controller = LearnedController(policy, cfg.model)
    else:
        try:
            controller = FilteredController(policy, cfg.model, filter_config, cbf if kind == "cbf" else None)
        except ValueError as err:
            raise ControllerError(f"filter {kind} on {contents.directory}: {err}") from None
    return ResolvedController(join_method(cfg.algo, kind), controller, cfg.robot, kind, contents.directory,
                              contents.weights_sha256, cfg, cbf)  # fmt: skip


def _marl(name, method, kind, checkpoint: Path, robot, device, dtype) -> ResolvedController:
    """The actor of a MARL checkpoint (:mod:`egcbf.marl`) as a controller; no run-time filter wraps it yet."""
    import hashlib

    from ..marl.checkpoint import WEIGHTS_FILE
    from ..marl.controller import load_marl_controller

    controller = load_marl_controller(checkpoint, device=device, dtype=dtype)
    cfg = controller.config
    if method not in (POLICY, cfg.algo):
        raise ControllerError(f"{name}: {checkpoint} holds a {cfg.algo} policy, not {method}")
    if robot not in (None, cfg.robot):
        raise ControllerError(f"robot {robot} but the checkpoint's policy drives a {cfg.robot}")
    if kind != "none":
        raise ControllerError(f"{name}: the run-time filters wrap the graph policies; a {cfg.algo} actor runs alone")
    digest = hashlib.sha256((checkpoint / WEIGHTS_FILE).read_bytes()).hexdigest()
    return ResolvedController(cfg.algo, controller, cfg.robot, "none", checkpoint, digest, cfg)


def _hand_crafted(name, method, kind, robot, filter_config, options) -> ResolvedController:
    """A hand-crafted controller of ``robot``, or the nominal command behind a filter."""
    from .filters import FilteredController

    if robot not in ROBOTS:
        raise ControllerError(f"unknown robot {robot!r}; choose one of {sorted(ROBOTS)}")
    hand_crafted = robot_controllers(robot)
    if method not in hand_crafted:
        learned = f" (a learned method needs its checkpoint, or use {POLICY!r} with one)" if method != POLICY else ""
        raise ControllerError(
            f"{name}: unknown controller {method!r} for the {robot}{learned}; its hand-crafted ones: "
            f"{sorted(hand_crafted)}"
        )
    if kind == "none":
        try:
            return ResolvedController(name, make_controller(method, robot=robot, **options), robot)
        except (TypeError, ValueError) as err:
            raise ControllerError(f"{name}: {err}") from None
    if method != "nominal" or kind == "cbf":
        raise ControllerError(
            f"{name}: a filter filters a learned policy's commands (give its checkpoint) or, as an ablation, the "
            "nominal controller's (nominal:FILTER; not with cbf, which reads a checkpoint's CBF)"
        )
    if options:
        raise ControllerError(f"{name}: {sorted(options)} set a hand-crafted controller, not a filter")
    try:
        return ResolvedController(name, FilteredController(None, None, filter_config), robot, kind)
    except ValueError as err:
        raise ControllerError(f"{name}: {err}") from None
