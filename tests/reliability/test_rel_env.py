"""egcbf inputs: states, goals, obstacles and controls are validated where they enter the simulator; coincident
agents get a defined CBF row; impossible swarm sizes are refused with the numbers."""

import numpy as np
import pytest
import torch

from egcbf.env import EnvConfig, SwarmEnv, SwarmState
from egcbf.env.obstacles import Obstacles
from egcbf.env.swarm import NonFiniteInputError
from egcbf.robots.quadrotor import dynamics as dyn
from egcbf.robots.quadrotor.barriers import BarrierConfig, obstacle_constraints, pair_constraints

F64 = torch.float64


@pytest.fixture
def env():
    return SwarmEnv(EnvConfig(num_agents=4, area_size=2.0, num_obstacles=2, max_steps=3), dtype=F64)


def _hover(env):
    return dyn.hover_control(env.config.params, 1, 4, dtype=F64)


def _with(state, x=None, goals=None, centers=None, radii=None):
    obs = Obstacles(
        state.obstacles.centers if centers is None else centers, state.obstacles.radii if radii is None else radii
    )
    return SwarmState(state.x if x is None else x, state.goals if goals is None else goals, obs, 0)


def test_nan_goal_is_refused(env):
    s = env.reset(0)
    goals = s.goals.clone()
    goals[0, 2, 1] = float("nan")
    with pytest.raises(ValueError, match=r"goals hold NaN or inf \(first: environment 0, agent 2\)"):
        env.step(_with(s, goals=goals), _hover(env))


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_obstacle_centre_is_refused(env, value):
    s = env.reset(0)
    c = s.obstacles.centers.clone()
    c[0, 1, 0] = value
    with pytest.raises(ValueError, match=r"obstacle centers hold NaN or inf \(first: environment 0, obstacle 1\)"):
        env.step(_with(s, centers=c), _hover(env))


@pytest.mark.parametrize("value", [-0.1, 0.0, float("nan"), float("inf")])
def test_bad_obstacle_radius_is_refused(env, value):
    s = env.reset(0)
    r = s.obstacles.radii.clone()
    r[0, 0] = value
    with pytest.raises(ValueError, match="obstacle radii must be finite and > 0"):
        env.step(_with(s, radii=r), _hover(env))


def test_invalid_attitude_is_refused(env):
    s = env.reset(0)
    x = s.x.clone()
    x[0, 1, dyn.ROT] = 2 * x[0, 1, dyn.ROT]  # a scaled matrix: not a rotation
    with pytest.raises(ValueError, match="R is not a rotation"):
        env.step(_with(s, x=x), _hover(env))


def test_nan_state_is_a_non_finite_input(env):
    s = env.reset(0)
    x = s.x.clone()
    x[0, 3, dyn.V] = float("nan")
    with pytest.raises(NonFiniteInputError, match="non-finite values in v"):
        env.step(_with(s, x=x), _hover(env))


@pytest.mark.parametrize("value", [float("inf"), -float("inf"), float("nan")])
def test_non_finite_control_is_refused(env, value):
    s = env.reset(0)
    u = _hover(env)
    u[0, 2, 1] = value
    with pytest.raises(ValueError, match=r"control u holds NaN or inf at step 1 \(first \(env, agent\) = \(0, 2\)"):
        env.step(s, u)


def test_control_of_the_wrong_shape_is_refused(env):
    with pytest.raises(ValueError, match=r"control u must be \(1, 4, 4\)"):
        env.step(env.reset(0), torch.zeros(1, 4, 3, dtype=F64))


def test_valid_inputs_still_step(env):
    s, info = env.step(env.reset(0), _hover(env))
    assert s.t == 1 and torch.isfinite(s.x).all() and not info.collision.any()


def test_impossible_packing_names_the_numbers():
    env = SwarmEnv(EnvConfig(num_agents=5000, area_size=1.0, num_obstacles=0))
    with pytest.raises(ValueError, match=r"cannot place N=5000 agents .* densest sphere packing"):
        env.reset(0)


@pytest.mark.parametrize(
    "field, value",
    [("area_size", float("nan")), ("num_agents", 0), ("agent_radius", -1.0), ("dt", 0.0), ("max_steps", 0)],
)
def test_bad_env_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"EnvConfig.{field} must be"):
        EnvConfig(**{field: value})


# ------------------------------------------------------------------------------------------------ coincident agents
def test_coincident_agents_get_a_unit_push_along_z():
    pos = np.zeros((2, 3))
    vel = np.zeros((2, 3))
    rows = pair_constraints(pos, vel, np.array([[0], [1]]), BarrierConfig(cull_radius=1.0))
    assert np.allclose(rows.normal, [[0.0, 0.0, 1.0]])
    assert np.isfinite(rows.rhs).all() and np.isfinite(rows.h).all()  # a real constraint, not a zero row


def test_coincident_agents_with_relative_velocity_push_along_it():
    pos = np.ones((2, 3))
    vel = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    rows = pair_constraints(pos, vel, np.array([[0], [1]]), BarrierConfig(cull_radius=1.0))
    assert np.allclose(rows.normal, [[1.0, 0.0, 0.0]])


def test_agent_at_an_obstacle_centre_gets_a_defined_row():
    rows = obstacle_constraints(
        np.ones((1, 3)), np.zeros((1, 3)), np.ones((1, 3)), np.array([0.2]), BarrierConfig(cull_radius=1.0)
    )
    assert len(rows) == 1 and np.allclose(np.linalg.norm(rows.normal, axis=-1), 1.0)


def test_separated_agents_rows_are_unchanged():
    pos = np.array([[0.0, 0.0, 0.0], [0.3, 0.4, 0.0]])
    rows = pair_constraints(pos, np.zeros((2, 3)), np.array([[0], [1]]), BarrierConfig(cull_radius=1.0))
    assert np.allclose(rows.normal, [[-0.6, -0.8, 0.0]])


@pytest.mark.parametrize("name", ["ccbf", "dcbf"])
def test_cbf_qps_refuse_an_entering_state_with_a_nan_obstacle(env, name):
    from egcbf.control.controllers import make_controller

    s = env.reset(0)
    c = s.obstacles.centers.clone()
    c[0, 0, 2] = float("nan")
    with pytest.raises(ValueError, match="obstacle centers hold NaN"):
        make_controller(name)(_with(s, centers=c), env.config)


@pytest.mark.parametrize("name", ["ccbf", "dcbf"])
def test_cbf_qps_give_finite_controls_for_coincident_agents(env, name):
    from egcbf.control.controllers import make_controller

    s = env.reset(0)
    x = s.x.clone()
    x[0, 1, dyn.P] = x[0, 0, dyn.P]  # agents 0 and 1 at exactly the same point
    u, _ = make_controller(name)(_with(s, x=x), env.config)
    assert u.shape == (1, 4, 4) and torch.isfinite(u).all()
