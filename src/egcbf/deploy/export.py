"""Export one agent's learned controller to a self-contained file a robot can run: TorchScript or ONNX.

The exported computation is :class:`egcbf.deploy.agent.AgentPolicy`: one agent's observation in fixed shapes with
validity masks, to its body control and command. The file holds the weights, the group actions (the agent's frame
from its attitude, the canonicalization), the nominal controller and, for the acceleration interface, the attitude
loop that turns the command into torque and thrust: nothing else is needed on board. ONNX files run under
onnxruntime alone (no torch, no egcbf); TorchScript files under ``torch.jit.load``.

    egcbf export --checkpoint checkpoints/egcbf+ --format onnx --out egcbf+.onnx
    egcbf export --checkpoint checkpoints/egcbf+ --format torchscript --out egcbf+.pt --max-neighbours 20

Inputs and outputs (float32; names as in the ONNX graph, positional in TorchScript; ``K = max_neighbours``,
``H = max_hits``, ``S`` and ``d`` the robot's state and space dimensions; world frame, SI units):

=================== =========== =====================================================================================
``state``           ``(S,)``    the agent's own state (quadrotor: ``[p, R row-major, v, w]``)
``goal``            ``(d,)``    its goal position
``neighbours``      ``(K, S)``  the states its neighbours broadcast, any order; unused rows any finite numbers
``neighbour_valid`` ``(K,)``    bool: the row holds a neighbour (used only if also closer than ``comm_radius``)
``hits``            ``(H, d)``  its LiDAR hit points; unused rows any finite numbers
``hit_valid``       ``(H,)``    bool: the row holds a hit
``u``               ``(c,)``    output: the body control (quadrotor: torque N m, body frame, and thrust N)
``command``         ``(k,)``    output: the policy's command in its interface's units (accel: acceleration / 5 m/s^2)
=================== =========== =====================================================================================

With more neighbours or hits than rows, pass the nearest (as :class:`egcbf.deploy.agent.AgentController` does). The
layout, limits and the checkpoint's identity are written beside the model: into the ONNX file's metadata
(``metadata_props``, key ``egcbf``), the TorchScript file's extra file ``egcbf.json``, and ``OUT.json``.
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
import logging
import warnings
from pathlib import Path

import torch
from torch import Tensor

from ..io.atomic import write_json_atomic
from ..nn.attention import EdgeAttention
from .agent import AgentController, AgentPolicy

__all__ = ["FORMATS", "INPUT_NAMES", "OUTPUT_NAMES", "example_inputs", "export_controller", "exportable", "layout"]

FORMATS = ("torchscript", "onnx")
INPUT_NAMES = ("state", "goal", "neighbours", "neighbour_valid", "hits", "hit_valid")
OUTPUT_NAMES = ("u", "command")
#: the ONNX operator set written (ScatterElements with max reduction needs 18)
OPSET = 18


def exportable(module: AgentPolicy) -> AgentPolicy:
    """A float32 copy of ``module`` in eval mode without gradients, with every attention layer on its per-edge path
    (dense and scatter operations only; :class:`egcbf.nn.attention.EdgeAttention`); the results are the same."""
    out = copy.deepcopy(module).to(torch.float32).eval()
    for m in out.modules():
        if isinstance(m, EdgeAttention):
            m.receiver_side = False
    for p in out.parameters():
        p.requires_grad_(False)
    return out


def example_inputs(module: AgentPolicy, env_config=None, seed: int = 0) -> tuple[Tensor, ...]:
    """Inputs of the right shapes and dtypes for ``module``: agent 0 of a random scene of ``1 + K`` agents (the
    others its neighbours, drawn nearly without separation in a square of side ``comm_radius``: most are in range),
    random hits around it, about half the rows valid. ``env_config``: the checkpoint's environment (its robot's
    parameters; default: the robot's defaults). For tracing, and to check a file."""
    import dataclasses

    from ..env import EnvConfig, SwarmEnv

    robot, k, h = module.robot, module.max_neighbours, module.max_hits
    base = env_config if env_config is not None else EnvConfig.for_robot(robot.name, num_agents=1)
    cfg = dataclasses.replace(base, num_agents=1 + k, num_envs=1, area_size=module.comm_radius, num_obstacles=0,
                              start_separation=0.05, max_travel=None, scene="uniform", scene_yaw=0.0)  # fmt: skip
    state = SwarmEnv(cfg, dtype=torch.float32).reset(seed)
    g = torch.Generator().manual_seed(seed)
    x, p = state.x[0], robot.positions(state.x[0, 0])
    hits = p + 0.8 * (torch.rand(h, robot.dim, generator=g) - 0.5)
    valid_n, valid_h = torch.rand(k, generator=g) < 0.5, torch.rand(h, generator=g) < 0.5
    return x[0], state.goals[0, 0], x[1:], valid_n, hits, valid_h


def layout(ctrl: AgentController, checkpoint: str | Path | None = None) -> dict:
    """The file's interface: names, shapes and dtypes of inputs and outputs, limits and sensing settings."""
    m = ctrl.module
    robot = m.robot
    s, d, k, h = robot.state_dim, robot.dim, m.max_neighbours, m.max_hits
    shapes = {"state": [s], "goal": [d], "neighbours": [k, s], "neighbour_valid": [k], "hits": [h, d],
              "hit_valid": [h], "u": [robot.control_dim], "command": [m.interface.dim]}  # fmt: skip
    info = {
        "format": "egcbf agent controller 1",
        "robot": robot.name,
        "interface": ctrl.model_config.interface,
        "group": ctrl.model_config.group,
        "inputs": {n: {"shape": shapes[n], "dtype": "bool" if n.endswith("valid") else "float32"} for n in INPUT_NAMES},
        "outputs": {n: {"shape": shapes[n], "dtype": "float32"} for n in OUTPUT_NAMES},
        "max_neighbours": k,
        "max_hits": h,
        "comm_radius": m.comm_radius,
        "lidar_range": m.lidar_range,  # hits farther away are ignored (the training rays' length)
        "trained_lidar_max_hits": ctrl.env_config.lidar_max_hits,
        "control_period_s": ctrl.env_config.dt,
        "command_unit": getattr(m.interface, "accel_unit", None),  # the acceleration interface's A (m/s^2)
    }
    if checkpoint is not None:
        from ..train.checkpoint import find_checkpoint, sha256

        ckpt = find_checkpoint(checkpoint, prefer_best=True)
        info["checkpoint"] = str(checkpoint)
        info["checkpoint_sha256"] = sha256(ckpt / "model.safetensors")
    return info


def export_controller(ctrl: AgentController, fmt: str, out: str | Path, checkpoint: str | Path | None = None) -> Path:
    """Write ``ctrl``'s fixed-shape module to ``out`` in format ``fmt`` (``"torchscript"`` or ``"onnx"``), with its
    :func:`layout` inside the file and in ``out`` + ``.json``; checks the written file against the PyTorch module on
    :func:`example_inputs` before returning (a file that disagrees is removed and an error raised)."""
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {fmt!r}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    module = exportable(ctrl.module)
    args = example_inputs(module, ctrl.env_config)
    info = layout(ctrl, checkpoint)
    with torch.no_grad():
        expected = module(*args)
    tmp = out.with_name(out.name + ".tmp")
    try:
        with warnings.catch_warnings():  # tracing warns about every Python value it records as a constant
            warnings.simplefilter("ignore")
            if fmt == "torchscript":
                with torch.no_grad():
                    traced = torch.jit.trace(module, args, check_trace=False)
                torch.jit.save(traced, str(tmp), _extra_files={"egcbf.json": json.dumps(info)})
                got = torch.jit.load(str(tmp))(*args)
            else:
                _export_onnx(module, args, tmp, info)
                got = run_onnx(tmp, args)
        for name, a, b in zip(OUTPUT_NAMES, got, expected):
            err = (torch.as_tensor(a) - b).abs().max().item()
            if not err <= 1e-5:
                raise RuntimeError(f"the exported {fmt} file's {name} differs from the PyTorch module's by {err:.3g}")
    except BaseException:
        tmp.unlink(missing_ok=True)  # never leave a half-written or unchecked file
        raise
    write_json_atomic(out.with_name(out.name + ".json"), info)
    tmp.replace(out)
    return out


@contextlib.contextmanager
def _quiet_exporter():
    """The ONNX exporter prints its progress and logs warnings about packages it does not need (torchvision)."""
    loggers = [logging.getLogger(n) for n in ("torch.onnx", "torch.export", "onnxscript", "onnx_ir")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def _export_onnx(module: AgentPolicy, args: tuple, path: Path, info: dict) -> None:
    import onnx

    with _quiet_exporter():
        program = torch.onnx.export(module, args, dynamo=True, opset_version=OPSET, input_names=list(INPUT_NAMES),
                                    output_names=list(OUTPUT_NAMES), external_data=False, verbose=False)  # fmt: skip
    model = program.model_proto
    entry = model.metadata_props.add()
    entry.key, entry.value = "egcbf", json.dumps(info)
    onnx.save_model(model, str(path))


def run_onnx(path: str | Path, args: tuple) -> list:
    """Run an exported ONNX file under onnxruntime on ``args`` (tensors or arrays, in :data:`INPUT_NAMES` order)."""
    import numpy as np
    import onnxruntime

    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    feeds = {n: np.asarray(a.numpy() if isinstance(a, Tensor) else a) for n, a in zip(INPUT_NAMES, args)}
    return session.run(list(OUTPUT_NAMES), feeds)
