"""The agents' disturbance observer (``egcbf.faults``, ``dist_obs``) and the robots' disturbance rejection
(``Robot.reject_disturbance``): zero disturbance changes nothing, the quadrotor's rejection is the attitude
controller's answer to the lowered target to first order, the estimate converges to a constant wind at its stated
rate, and hovering in wind keeps its position with the observer and not without.

Tolerances: float64 equivariance 1e-9, float32 1e-4 of the actuator bounds (stated); the first-order claim as a
ratio: the error at ``accel`` is below ``0.05 |accel|`` times the change of the command it corrects (second order).
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from dyn_helpers import F32, F64, random_states
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.env import EnvConfig, SwarmEnv, SwarmState
from egcbf.faults import FaultConfig, FaultProcess
from egcbf.faults.onboard import DIST_OBS_TAU, Onboard
from egcbf.robots import Robot, make_robot
from egcbf.robots.quadrotor.dynamics import DEFAULT_PARAMS, GROUP, STATE_TYPE
from egcbf.robots.quadrotor.nominal import desired_heading, reject_disturbance, track_acceleration
from groupcanon import FieldType
from groupcanon.features import Vector
from groupcanon.testing import strategies as gst

B = 16
ACCEL_TYPE = FieldType(GROUP, {"a": Vector(3)})
SCALE = torch.tensor([*DEFAULT_PARAMS.max_torque, DEFAULT_PARAMS.max_thrust], dtype=F64)


def _commands(seed: int, dtype=F64) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    x = random_states(seed, (B,), dtype, rate=3.0)
    a = (2.0 * torch.rand(B, 3, generator=gen, dtype=F64) - 1.0).to(dtype)
    d = (1.5 * torch.randn(B, 3, generator=gen, dtype=F64)).to(dtype)
    return x, track_acceleration(x, a), d


# ------------------------------------------------------------------------------------ the quadrotor's rejection
@given(seed=gst.seeds())
def test_zero_disturbance_returns_the_command_bit_for_bit(seed):
    x, u, _ = _commands(seed)
    assert torch.equal(reject_disturbance(x, u, torch.zeros(B, 3, dtype=F64)), u)


@given(g=gst.elements(GROUP, batch=(B,)), seed=gst.seeds())
def test_rejection_is_equivariant(g, seed):
    """A rotated (and shifted) agent under the rotated disturbance gets the same body-frame command."""
    x, u, d = _commands(seed)
    out = reject_disturbance(x, u, d)
    assert float((reject_disturbance(STATE_TYPE.act(g, x), u, ACCEL_TYPE.act(g, d)) - out).abs().max()) < 1e-9


@given(g=gst.elements(GROUP, batch=(B,), dtype=F32), seed=gst.seeds())
def test_rejection_is_equivariant_float32(g, seed):
    x, u, d = _commands(seed, F32)
    out = reject_disturbance(x, u, d)
    err = (reject_disturbance(STATE_TYPE.act(g, x), u, ACCEL_TYPE.act(g, d)) - out).abs() / SCALE.to(F32)
    assert float(err.max()) < 1e-4


def _at_its_attitude(yaw: float, horizontal: float, vertical: float, across: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """An agent (spinning, moving) whose attitude is the one ``track_acceleration`` asks for the acceleration
    ``a`` (horizontal along its heading, a pitch, or ``across`` it, a roll: both leave the heading hold nothing more
    to ask), and ``a``."""
    c, s = math.cos(yaw), math.sin(yaw)
    along = [-horizontal * s, horizontal * c, vertical] if across else [horizontal * c, horizontal * s, vertical]
    a = torch.tensor(along, dtype=F64)
    b3 = a + torch.tensor([0.0, 0.0, DEFAULT_PARAMS.gravity], dtype=F64)
    b3 = b3 / b3.norm()
    b1c = desired_heading(torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=F64))
    b2 = torch.linalg.cross(b3, b1c, dim=-1)
    b2 = b2 / b2.norm()
    R = torch.stack((torch.linalg.cross(b2, b3, dim=-1), b2, b3), dim=-1)
    x = torch.cat((torch.tensor([1.0, 2.0, 0.5]), R.reshape(9), torch.tensor([0.2, -0.1, 0.3, 0.1, -0.2, 0.05])))
    return x.to(F64), a


@settings(deadline=None)
@given(yaw=st.floats(-math.pi, math.pi), horizontal=st.floats(-2.0, 2.0), vertical=st.floats(-2.0, 2.0),
       direction=st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda v: sum(c * c for c in v) > 0.1),
       size=st.sampled_from([1e-2, 1e-3]), across=st.booleans())  # fmt: skip
def test_rejection_is_the_lowered_target_to_first_order(yaw, horizontal, vertical, direction, size, across):
    """``reject_disturbance(x, track_acceleration(x, a), d) = track_acceleration(x, a - d) + O(|d|^2)`` in thrust
    and tilt torques; the yaw torque keeps the command's heading (track_acceleration's heading hold reacts to the
    tilt at first order, which the rejection leaves out by design)."""
    x, a = _at_its_attitude(yaw, horizontal, vertical, across)
    d = size * torch.tensor(direction, dtype=F64)
    u = track_acceleration(x, a, clip=False)
    lowered = track_acceleration(x, a - d, clip=False)
    err = (reject_disturbance(x, u, d, clip=False) - lowered)[[0, 1, 3]]
    change = float((lowered - u)[[0, 1, 3]].abs().max())
    assert float(err.abs().max()) <= 0.05 * float(d.norm()) * change + 1e-15


def test_planar_robots_cancel_the_disturbance_along_their_heading():
    for name in ("unicycle", "dubins_car"):
        robot = make_robot(name)
        x = torch.tensor([[0.0, 0.0, 0.6, 0.8, 0.3]], dtype=F64)
        u = torch.tensor([[0.1, 0.2]], dtype=F64)
        out = robot.reject_disturbance(x, u, torch.tensor([[0.5, 0.0]], dtype=F64))
        assert torch.allclose(out, torch.tensor([[0.1, 0.2 - 0.3]], dtype=F64), atol=1e-15), name
        assert torch.equal(robot.reject_disturbance(x, u, torch.zeros(1, 2, dtype=F64)), u)


def test_point_masses_cancel_the_disturbance_and_the_single_integrator_cannot():
    x2, u2 = torch.zeros(1, 4, dtype=F64), torch.tensor([[0.1, -0.2]], dtype=F64)
    di = make_robot("double_integrator")
    assert torch.allclose(di.reject_disturbance(x2, u2, torch.tensor([[1.0, 2.0]], dtype=F64)),
                          u2 - di.params.mass * torch.tensor([[1.0, 2.0]], dtype=F64), atol=1e-15)  # fmt: skip
    drone = make_robot("linear_drone")
    x3, u3 = torch.zeros(1, 6, dtype=F64), torch.tensor([[0.1, -0.2, 0.3]], dtype=F64)
    a = torch.tensor([[1.0, 0.5, -2.0]], dtype=F64)
    assert torch.allclose(drone.xdot(x3, drone.reject_disturbance(x3, u3, a))[..., 3:] + a, drone.xdot(x3, u3)[..., 3:])
    with pytest.raises(NotImplementedError, match="reject_disturbance"):
        make_robot("single_integrator").reject_disturbance(x2[..., :2], u2, a[..., :2])


# ------------------------------------------------------------------------------------------------ the observer
CFG = EnvConfig(num_agents=4, num_envs=2, area_size=3.0, num_obstacles=0, max_steps=400)
ROBOT = make_robot("quadrotor")


def _hover(steps: int, faults: FaultConfig):
    """Agents told to hold their start positions for ``steps`` under ``faults``: their drift (B, N, 3) and the
    fault process."""
    env = SwarmEnv(CFG, dtype=F64)
    state = env.reset(5)
    start = ROBOT.positions(state.x).clone()
    state = SwarmState(state.x, start, state.obstacles, state.t, state.robot)
    proc = FaultProcess(faults, CFG, ROBOT, [1, 2], dtype=F64)
    for _ in range(steps):
        seen = proc.observe(state)
        state, _ = env.step(state, proc.actuate(ROBOT.nominal_control(seen.x, seen.goals), state))
        state = proc.push(state)
    return ROBOT.positions(state.x) - start, proc


def test_the_estimate_converges_to_a_constant_wind_at_its_rate():
    """Exact estimates, constant wind ``w``: after ``k`` updates the estimate is ``w (1 - (1 - beta)^k)``,
    ``beta = 1 - exp(-dt / DIST_OBS_TAU)`` (each measured acceleration is ``w`` exactly: the model is the
    simulator's)."""
    wind = (0.6, -0.4, 0.3)
    steps = 30
    _, proc = _hover(steps, FaultConfig(wind=wind, dist_obs=1))
    beta = 1.0 - math.exp(-CFG.dt / DIST_OBS_TAU)
    want = torch.tensor(wind, dtype=F64) * (1.0 - (1.0 - beta) ** (steps - 1))
    assert torch.allclose(proc.disturbance, want.expand_as(proc.disturbance), rtol=0, atol=1e-9)


@pytest.mark.parametrize("faults", [dict(wind=(1.0, 0.0, 0.0), gust=0.0), dict(thrust_gain=0.3)])
def test_hovering_in_wind_or_with_a_thrust_error_holds_its_position_with_the_observer(faults):
    """The nominal controller's proportional loop leaves a steady offset (``|w| / k_x`` in a wind ``w``, a height
    error under a thrust gain error); with the observer it shrinks to a tenth within 10 s."""
    without, _ = _hover(400, FaultConfig(**faults))
    with_obs, _ = _hover(400, FaultConfig(**faults, dist_obs=1))
    off, on = float(without.norm(dim=-1).max()), float(with_obs.norm(dim=-1).max())
    assert off > 0.05 and on < 0.1 * off, (off, on)


def test_a_robot_without_rejection_is_refused():
    class Stiff(type(ROBOT)):
        reject_disturbance = Robot.reject_disturbance

    with pytest.raises(ValueError, match="dist_obs: the disturbance observer needs"):
        FaultProcess(FaultConfig(wind=(1.0, 0.0, 0.0), dist_obs=1), CFG, Stiff(), [1], dtype=F64)
    FaultProcess(FaultConfig(wind=(1.0, 0.0, 0.0)), CFG, Stiff(), [1], dtype=F64)  # only the observer needs it


def test_one_onboard_per_agent_is_what_the_simulator_runs_for_the_swarm():
    """A robot running its own :class:`egcbf.faults.onboard.Onboard` on its ``(S,)`` state does what the fault process
    does for it in the swarm: the same trajectories (two periods of actuation delay with the prediction, the observer,
    wind and thrust errors acting)."""
    faults = FaultConfig(act_delay=2, act_predict=1, dist_obs=1, wind=(0.5, 0.2, 0.0), thrust_gain=0.2)
    env = SwarmEnv(CFG, dtype=F64)
    start = env.reset(7)
    swarm, physics = (FaultProcess(f, CFG, ROBOT, [1, 2], dtype=F64)
                      for f in (faults, dataclasses.replace(faults, act_predict=0, dist_obs=0)))  # fmt: skip
    robots = [[Onboard(ROBOT, CFG, act_delay=2, predict=True, observe_disturbance=True) for _ in range(4)]
              for _ in range(2)]  # fmt: skip
    a, b = start, start
    for _ in range(12):
        seen = swarm.observe(a)
        a, _ = env.step(a, swarm.actuate(ROBOT.nominal_control(seen.x, seen.goals), a))
        a = swarm.push(a)
        seen = physics.observe(b)  # the physical faults only: each agent handles them itself
        sent = []
        for i, row in enumerate(robots):
            x_for = [agent.estimate(seen.x[i, j], seen.goals[i, j]) for j, agent in enumerate(row)]
            sent.append([agent.command(ROBOT.nominal_control(x, seen.goals[i, j]))
                         for j, (agent, x) in enumerate(zip(row, x_for))])  # fmt: skip
        u = torch.stack([torch.stack(r) for r in sent])
        b, _ = env.step(b, physics.actuate(u, b))
        b = physics.push(b)
        assert torch.allclose(a.x, b.x, rtol=0, atol=1e-10)
    assert swarm.disturbance.abs().max() > 0.1  # the observer was at work


def test_onboard_refuses_bad_settings_and_a_command_before_an_estimate():
    with pytest.raises(ValueError, match="act_delay"):
        Onboard(ROBOT, CFG, act_delay=-1)
    with pytest.raises(ValueError, match="tau"):
        Onboard(ROBOT, CFG, tau=0.0)
    with pytest.raises(RuntimeError, match=r"before Onboard\.estimate"):
        Onboard(ROBOT, CFG, act_delay=1, predict=True).command(torch.zeros(4, dtype=F64))
    agent = Onboard(ROBOT, CFG, observe_disturbance=True)
    x = SwarmEnv(CFG, dtype=F64).reset(1).x[0, 0]
    with pytest.raises(ValueError, match="needs x"):
        agent.estimate(x[:12], torch.zeros(3, dtype=F64))
    agent.estimate(x, torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match="changed shape"):
        agent.estimate(x[None], torch.zeros(1, 3, dtype=F64))


def test_non_cooperative_agents_and_exact_estimates_leave_the_estimate_at_zero():
    """Without a physical disturbance the observer measures nothing, whatever the agents send: non-cooperative
    agents' own commands are what they record (their override comes before the record), delayed and predicted."""
    faults = FaultConfig(noncoop=0.5, noncoop_mode="straight", act_delay=2, act_predict=1, dist_obs=1)
    env = SwarmEnv(CFG, dtype=F64)
    state = env.reset(3)
    proc = FaultProcess(faults, CFG, ROBOT, [1, 2], dtype=F64)
    for _ in range(8):
        seen = proc.observe(state)
        state, _ = env.step(state, proc.actuate(ROBOT.nominal_control(seen.x, seen.goals), state))
    assert bool(proc.noncoop.any()) and torch.equal(proc.disturbance, torch.zeros_like(proc.disturbance))


def test_parking_near_the_goal_is_not_taken_for_a_disturbance():
    """A robot that parks at its goal (the Dubins car) parks on its true position, its model on the noisy estimate;
    near the goal the observer holds its estimate rather than read the mismatch as a push."""
    robot = make_robot("dubins_car")
    cfg = EnvConfig.for_robot("dubins_car", num_agents=4, num_envs=2, max_steps=300)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(4)
    proc = FaultProcess(FaultConfig(pos_noise=0.01, dist_obs=1), cfg, robot, [1, 2], dtype=F64)
    largest = 0.0
    for _ in range(300):
        seen = proc.observe(state)
        state, _ = env.step(state, proc.actuate(robot.nominal_control(seen.x, seen.goals), state))
        largest = max(largest, float(proc.disturbance.norm(dim=-1).max()))
    gap = torch.linalg.vector_norm(robot.positions(state.x) - state.goals, dim=-1)
    assert bool((gap < robot.goal_freeze_radius).any())  # agents did park
    assert largest < 0.1, largest  # 0.6 m/s^2 when the observer read parking as a push
