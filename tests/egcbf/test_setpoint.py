"""The firmware-like setpoint tracker (a Mellinger controller at an inner rate) and ``egcbf eval --low-level``.

Tolerances: equivariance in float64 within 1e-9 (states of size ~1-10 after 13 inner steps); hover exact to 1e-12;
tracking a constant acceleration along its reference trajectory within 0.05 m/s^2 per component after 2 s (the
position loop's slow pole, ~3.7 rad/s, has settled to ~1 %).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from dyn_helpers import F64, random_states
from hypothesis import given, settings
from typer.testing import CliRunner

from egcbf.cli import app
from egcbf.control.controllers import make_controller
from egcbf.env import EnvConfig
from egcbf.evaluate.episodes import run_episodes
from egcbf.robots.quadrotor.dynamics import DEFAULT_DT, GROUP, STATE_TYPE, hover_state
from egcbf.robots.quadrotor.setpoint import MellingerGains, inner_steps, setpoint_control, track_setpoint
from groupcanon.features import Point, Vector
from groupcanon.field_type import FieldType
from groupcanon.testing import strategies as gst

B = 16
SETPOINT_TYPE = FieldType(GROUP, {"p": Point(3), "v": Vector(3), "a": Vector(3)})
CHECKPOINT = Path(__file__).resolve().parents[2] / "checkpoints" / "egcbf+"


def _setpoints(seed: int, batch=(B,)):
    g = torch.Generator().manual_seed(seed + 11)
    p = torch.rand(*batch, 3, generator=g, dtype=F64) * 4
    v = torch.randn(*batch, 3, generator=g, dtype=F64)
    a = torch.randn(*batch, 3, generator=g, dtype=F64) * 3
    yaw = (torch.rand(*batch, generator=g, dtype=F64) * 2 - 1) * math.pi
    return p, v, a, yaw


@settings(deadline=None, max_examples=25)
@given(g=gst.elements(GROUP, batch=(B,)), seed=gst.seeds())
def test_tracker_is_se2xr_equivariant(g, seed):
    """track_setpoint(phi_g x, g . setpoint) == phi_g track_setpoint(x, setpoint); the control is invariant."""
    x = random_states(seed, (B,), rate=3.0)
    p, v, a, yaw = _setpoints(seed)
    x1, u1 = track_setpoint(x, p, v, a, yaw)
    sp = SETPOINT_TYPE.act(g, torch.cat((p, v, a), -1))
    theta = torch.atan2(g[..., 1], g[..., 0])
    x2, u2 = track_setpoint(STATE_TYPE.act(g, x), sp[..., 0:3], sp[..., 3:6], sp[..., 6:9], yaw + theta)
    assert float((x2 - STATE_TYPE.act(g, x1)).abs().max()) < 1e-9
    assert float((u2 - u1).abs().max()) < 1e-9


def test_inner_steps_cover_the_control_period():
    assert inner_steps(0.025, 500.0) == 13  # 12.5 firmware ticks: 13 equal steps of 1.92 ms
    assert inner_steps(0.02, 500.0) == 10
    with pytest.raises(ValueError, match="inner_rate"):
        inner_steps(0.025, 0.0)


def test_default_gains_are_the_firmware_defaults_in_si_units():
    g = MellingerGains()
    assert g == MellingerGains.from_firmware()
    assert (g.kp_xy, g.kd_xy, g.kp_z, g.kd_z) == (0.4, 0.2, 1.25, 0.4)
    assert g.kd_omega_rp == 0.0 and MellingerGains.from_firmware(kd_omega_rp=True).kd_omega_rp > 0
    with pytest.raises(ValueError, match="kp_xy"):
        MellingerGains(kp_xy=-1.0)


def test_hover_setpoint_stays_put():
    """a_sp = 0, p_sp = p, v_sp = v at hover (refreshed every period, as the evaluation sends it): no motion."""
    p0 = torch.tensor([[1.0, 2.0, 3.0], [0.5, -1.0, 2.0]], dtype=F64)
    yaw = torch.tensor([0.3, -2.0], dtype=F64)
    x = hover_state(p0, yaw)
    for _ in range(40):  # 1 s
        x, u = track_setpoint(x, x[..., 0:3], x[..., 12:15], torch.zeros_like(p0), yaw)
    assert float((x - hover_state(p0, yaw)).abs().max()) < 1e-12
    assert float((u[..., :3]).abs().max()) < 1e-12
    assert torch.allclose(u[..., 3], torch.full((2,), 0.0299 * 9.81, dtype=F64))


def test_tracks_a_constant_acceleration_after_settling():
    """Along the constant-acceleration reference (p_sp = p0 + a t^2 / 2, v_sp = a t, a_sp = a), the realized
    acceleration over a control period is within 0.05 m/s^2 of ``a`` per component after 2 s."""
    p0 = torch.tensor([[1.0, 2.0, 3.0]], dtype=F64)
    a = torch.tensor([[1.0, -0.5, 0.3]], dtype=F64)
    yaw = torch.tensor([0.7], dtype=F64)
    x = hover_state(p0, yaw)
    for k in range(80):
        t = k * DEFAULT_DT
        x_next, _ = track_setpoint(x, p0 + 0.5 * a * t * t, a * t, a, yaw)
        realized = (x_next[..., 12:15] - x[..., 12:15]) / DEFAULT_DT
        x = x_next
    assert float((realized - a).abs().max()) < 0.05


def test_setpoint_control_zero_thrust_gives_no_moment():
    """As the firmware: no moment where the thrust along the body axis is not positive."""
    x = hover_state(torch.zeros(1, 3, dtype=F64))
    x[..., 15:18] = torch.tensor([1.0, -2.0, 0.5], dtype=F64)
    u = setpoint_control(x, x[..., 0:3], x[..., 12:15], torch.tensor([[0.0, 0.0, -20.0]], dtype=F64),
                         torch.zeros(1, dtype=F64))  # fmt: skip
    assert float(u.abs().max()) == 0.0


def test_setpoint_low_level_needs_an_acceleration_command():
    """A controller that returns body controls only cannot be flown through the tracker: a clear error."""
    cfg = EnvConfig(num_agents=2, max_steps=2)
    with pytest.raises(ValueError, match="accel_command"):
        run_episodes(make_controller("nominal"), cfg, [0], low_level="setpoint")
    with pytest.raises(ValueError, match="low_level"):
        run_episodes(make_controller("nominal"), cfg, [0], low_level="firmware")


def test_setpoint_low_level_is_for_the_quadrotor_only():
    cfg = EnvConfig.for_robot("double_integrator", num_agents=2, max_steps=2)
    with pytest.raises(ValueError, match="quadrotor"):
        run_episodes(make_controller("nominal", robot="double_integrator"), cfg, [0], low_level="setpoint")


@pytest.mark.skipif(not (CHECKPOINT / "model.safetensors").exists(), reason="the shipped checkpoint is absent")
def test_eval_records_the_setpoint_low_level(tmp_path):
    out = tmp_path / "sp"
    args = ["eval", "--checkpoint", str(CHECKPOINT), "--filter", "dcbf", "--num-agents", "4", "--episodes", "1",
            "--max-steps", "4", "--no-progress", "--threads", "1", "--low-level", "setpoint",
            "--out", str(out)]  # fmt: skip
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    meta = json.loads((out / "run.json").read_text())
    assert meta["low_level"] == "setpoint"
    assert meta["setpoint_tracker"]["inner_steps"] == 13
    assert meta["setpoint_tracker"]["gains"] == MellingerGains().to_dict()
    assert json.loads((out / "metrics.json").read_text())[0]["low_level"] == "setpoint"


def test_eval_rejects_the_setpoint_low_level_without_an_acceleration_command(tmp_path):
    res = CliRunner().invoke(app, ["eval", "--controller", "dcbf", "--num-agents", "4", "--episodes", "1",
                                   "--max-steps", "2", "--no-progress", "--low-level", "setpoint", "--out",
                                   str(tmp_path / "x")])  # fmt: skip
    assert res.exit_code != 0 and "body controls only" in res.output
