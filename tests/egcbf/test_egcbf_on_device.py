"""egcbf on ``--device`` (conftest; ``cuda`` in benchmarks/gpu_check.sh, ``cpu`` in CI): the simulator, the shipped
EGCBF+ policy, its run-time filters (the batched interior-point QPs on the device) and a training update, each in
float32 on the device against float64 on the CPU.

Tolerances (float32 against float64): states after 20 simulated steps within 1e-3 m and m/s; commands within
1e-3 of their scale (m/s^2 or N, N m); a filtered acceleration within 1e-2 m/s^2 (the interior-point method stops
at its own tolerance, 1e-6 relative, and float32 moves its iterates by more).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from egcbf.algo.config import TrainConfig
from egcbf.control.controllers import NominalController
from egcbf.control.filters import FilterConfig
from egcbf.control.resolve import resolve
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.train.checkpoint import load_controller, load_network
from egcbf.train.loop import train

pytestmark = pytest.mark.device

SHIPPED = Path(__file__).resolve().parents[2] / "checkpoints" / "egcbf+"
F32, F64 = torch.float32, torch.float64


def _scene(device, dtype, n: int = 32, area: float = 2.0, obstacles: int = 4):
    cfg = EnvConfig(num_agents=n, area_size=area, num_obstacles=obstacles, num_envs=1)
    env = SwarmEnv(cfg, device=device, dtype=dtype)
    return env, env.reset(3), cfg


def _close(a, b, atol: float):
    a, b = torch.as_tensor(a).detach().cpu().double(), torch.as_tensor(b).detach().cpu().double()
    scale = 1.0 + b.abs().max()
    assert (a - b).abs().max() <= atol * scale, f"{(a - b).abs().max():.3g} > {atol} * {scale:.3g}"


def test_the_simulator_matches_float64_on_the_cpu(device):
    ends = []
    for dev, dtype in ((device, F32), (torch.device("cpu"), F64)):
        env, state, cfg = _scene(dev, dtype)
        ctrl = NominalController()
        for _ in range(20):
            u, _ = ctrl(state, cfg)
            state, _ = env.step(state, u)
        assert state.x.device.type == dev.type and state.x.dtype == dtype
        ends.append(state.x)
    _close(ends[0], ends[1], 1e-3)


def test_the_shipped_policy_matches_float64_on_the_cpu(device):
    us = []
    for dev, dtype in ((device, F32), (torch.device("cpu"), F64)):
        ctrl, _ = load_controller(SHIPPED, device=dev, dtype=dtype)
        _, state, cfg = _scene(dev, dtype)
        u, _ = ctrl(state, cfg)
        assert u.device.type == dev.type and u.dtype == dtype
        us.append(u)
    _close(us[0], us[1], 1e-3)


@pytest.mark.parametrize("kind", ["dcbf", "cbf"])
def test_the_filters_match_float64_on_the_cpu(device, kind):
    out = []
    for dev, dtype in ((device, F32), (torch.device("cpu"), F64)):
        ctrl = resolve(
            f"policy:{kind}", SHIPPED, filter_config=FilterConfig(kind=kind), device=dev, dtype=dtype
        ).controller
        _, state, cfg = _scene(dev, dtype)
        u, info = ctrl(state, cfg)
        assert u.device.type == dev.type and torch.isfinite(u).all()
        out.append(info["a_safe"])
    _close(out[0], out[1], 1e-2)


def test_two_training_updates_run_on_the_device(tmp_path, device):
    cfg = dataclasses.replace(TrainConfig.preset("egcbf+", "tiny", steps=2), device=str(device))
    learner = train(cfg, tmp_path / "run", progress=False, log=lambda line: None)
    assert learner.step == 2
    p = next(learner.policy.parameters())
    assert p.device.type == device.type and all(torch.isfinite(q).all() for q in learner.policy.parameters())
    policy, _ = load_network(tmp_path / "run", "policy", "cpu", F64)  # its checkpoint loads anywhere
    assert all(torch.isfinite(q).all() for q in policy.parameters())
