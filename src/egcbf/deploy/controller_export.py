"""Export the recommended controller whole: one agent's policy behind the ``dcbf`` run-time filter, as a directory a
robot runs with numpy and onnxruntime alone.

    egcbf export --controller egcbf+:dcbf --checkpoint checkpoints/egcbf+ --out egcbf+-dcbf --max-neighbours 20

The directory (docs/deploy.md, "The whole controller"):

* ``policy.onnx``: the fixed-shape policy (:func:`egcbf.deploy.export.export_controller`), float32; its layout in
  ``policy.onnx.json``;
* ``controller.json``: the filter's settings (barrier, look-ahead, slack penalty, acceleration box, fallback), the
  robot's constants (mass, inertia, actuator limits, the attitude loop's gains) and the policy's layout and sensing
  limits (:func:`controller_settings`);
* ``egcbf_runtime.py``: a copy of :mod:`egcbf.deploy.runtime`, the numpy filter and attitude loop around the ONNX
  policy (``Controller.load(DIR).step(...)``).

What is exported is :class:`egcbf.deploy.agent.AgentFilteredController`'s computation; before the directory is
kept, the runtime it holds is run on a test observation and compared with that PyTorch controller.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import shutil
import tempfile
from pathlib import Path
from types import ModuleType

import numpy as np
import torch

from ..io.atomic import write_json_atomic
from . import runtime
from .agent import AgentFilteredController
from .export import example_inputs, export_controller, layout

__all__ = ["CONTROLLER_FILES", "check_against", "controller_settings", "export_filtered_controller", "load_runtime"]

#: the files of an exported controller's directory
CONTROLLER_FILES = (runtime.POLICY_FILE, runtime.POLICY_FILE + ".json", runtime.SETTINGS_FILE, runtime.RUNTIME_FILE)
#: what the export's self-check accepts between the runtime (float32 ONNX policy) and the PyTorch controller: the
#: command in its units (1 = 5 m/s^2) and the body control
CHECK_TOL = 1e-4


def controller_settings(ctrl: AgentFilteredController, checkpoint: str | Path | None = None,
                        name: str | None = None) -> dict:  # fmt: skip
    """``controller.json``: what :mod:`egcbf.deploy.runtime` needs besides the ONNX policy, read from ``ctrl`` (the
    filter's own resolved settings, so that the export runs what the PyTorch controller runs).

    Raises:
        ValueError: a setting the runtime does not implement (another barrier kind than Wang et al.'s, a cap on
            neighbours or obstacles, LiDAR obstacle rows). The dcbf filter itself is the quadrotor's (its QP refuses
            another robot when it runs: the export's check).
    """
    qp, fcfg, env = ctrl._qp, ctrl.filter_config, ctrl.env_config
    barrier, bounds = qp.resolved(env)
    unsupported = {
        "barrier kind": (barrier.kind, "wang"),
        "barrier max_neighbors": (barrier.max_neighbors, None),
        "barrier max_obstacles": (barrier.max_obstacles, None),
        "obstacle_sensing": (fcfg.obstacle_sensing, "map"),
    }
    for what, (got, want) in unsupported.items():
        if got != want:
            raise ValueError(f"the exported runtime implements the dcbf filter with {what} = {want!r}, not {got!r}")
    gains = dataclasses.asdict(qp.config.gains)
    return {
        "format": runtime.FORMAT,
        "name": name or "policy:dcbf",
        "policy": {"file": runtime.POLICY_FILE, **layout(ctrl.controller, checkpoint)},
        "filter": {
            "kind": "dcbf",
            "lookahead": float(fcfg.lookahead),
            "penalty": {"w1": float(qp.config.penalty.w1), "w2": float(qp.config.penalty.w2)},
            "brake_gain": float(qp.config.brake_gain),
            "slack_tol": float(qp.config.slack_tol),
            "obstacle_sensing": "map",
            "barrier": {
                "kind": barrier.kind,
                "agent_radius": barrier.agent_radius,
                "margin": barrier.margin,
                "gamma": barrier.gamma,
                "brake_accel": barrier.brake_accel,
                "cull_radius": barrier.cull_radius,
                "obstacle_cull": barrier.obstacle_cull,
            },
            "bounds": {
                "horizontal": bounds.horizontal,
                "z_min": bounds.z_min,
                "z_max": bounds.z_max,
                "polygon": int(bounds.polygon),
            },
        },
        "robot": {
            "name": env.robot,
            "params": dataclasses.asdict(env.params),
            "gains": {k: (list(v) if isinstance(v, tuple) else v) for k, v in gains.items()},
        },
    }


def load_runtime(directory: str | Path) -> ModuleType:
    """The ``egcbf_runtime.py`` of an exported directory, imported from that file (not from the package)."""
    path = Path(directory) / runtime.RUNTIME_FILE
    spec = importlib.util.spec_from_file_location(f"egcbf_runtime_{abs(hash(str(path.resolve())))}", path)
    if spec is None or spec.loader is None:
        raise FileNotFoundError(f"{path}: not an importable runtime")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _check_scene(ctrl: AgentFilteredController, seed: int = 0):
    """A test observation: :func:`~egcbf.deploy.export.example_inputs`'s agent and neighbours, two sphere obstacles
    next to it and random realized accelerations (float32, as a robot's)."""
    state, goal, nbr, nbr_valid, hits, hit_valid = example_inputs(ctrl.controller.module, ctrl.env_config, seed)
    g = torch.Generator().manual_seed(seed)
    p = state[:3]
    centers = p + torch.tensor([[0.35, 0.0, 0.0], [0.0, -0.5, 0.1]])
    radii = torch.tensor([0.15, 0.2])
    acc = 0.5 * torch.randn(1 + nbr.shape[0], 3, generator=g)
    return state, goal, nbr, nbr_valid, hits, hit_valid, acc, (centers, radii)


def check_against(ctrl: AgentFilteredController, directory: str | Path, seed: int = 0) -> float:
    """Run the runtime in ``directory`` and ``ctrl`` on a test observation (:func:`_check_scene`); the largest
    difference of the filtered command and the body control (raises ``RuntimeError`` above :data:`CHECK_TOL`)."""
    state, goal, nbr, nbr_valid, hits, hit_valid, acc, obstacles = _check_scene(ctrl, seed)
    mod = load_runtime(directory)
    rt = mod.Controller.load(directory)
    u, info = rt.step(state.numpy(), goal.numpy(), nbr.numpy(), nbr_valid.numpy(), hits.numpy(), hit_valid.numpy(),
                      accelerations=acc.numpy(), obstacles=tuple(t.numpy() for t in obstacles))  # fmt: skip
    keep = torch.cat((torch.tensor([True]), nbr_valid))
    u_ref, ref = ctrl(state, goal, nbr[nbr_valid], hits[hit_valid], obstacles=obstacles, accelerations=acc[keep])
    err = max(float(np.abs(u - u_ref.double().numpy()).max()),
              float(np.abs(info["command"] - ref["command"].double().numpy()).max()))  # fmt: skip
    if not err <= CHECK_TOL or info["failed"] != ref["failed"]:
        raise RuntimeError(f"the exported controller differs from the PyTorch one by {err:.3g} (failed: "
                           f"{info['failed']} vs {ref['failed']}) on the test observation")  # fmt: skip
    return err


def export_filtered_controller(ctrl: AgentFilteredController, out: str | Path, checkpoint: str | Path | None = None,
                               name: str | None = None) -> Path:  # fmt: skip
    """Write ``ctrl`` (its policy as ONNX, :func:`controller_settings`, the runtime) into the directory ``out``
    (created if missing; the files of :data:`CONTROLLER_FILES` there are replaced), after checking the written
    runtime against ``ctrl`` (:func:`check_against`). Nothing is left in ``out`` when a step fails."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    settings = controller_settings(ctrl, checkpoint, name)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        export_controller(ctrl.controller, "onnx", tmp / runtime.POLICY_FILE, checkpoint)
        write_json_atomic(tmp / runtime.SETTINGS_FILE, settings)
        shutil.copyfile(runtime.__file__, tmp / runtime.RUNTIME_FILE)
        check_against(ctrl, tmp)
        out.mkdir(exist_ok=True)
        for f in CONTROLLER_FILES:
            (tmp / f).replace(out / f)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out
