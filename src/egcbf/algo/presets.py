"""The training presets: which method is which point of the method grid, and each preset's field values.

:meth:`egcbf.algo.config.TrainConfig.preset` builds a config from them (``TrainConfig.preset("egcbf+", "cpu")``); this
module holds only the tables and the recipes (plain dicts of :class:`egcbf.algo.config.TrainConfig` and
:class:`egcbf.nn.models.ModelConfig` fields), so that the config class stays one job.
"""

from __future__ import annotations

from typing import Any

from ..robots import DEFAULT_ROBOT, make_robot

__all__ = ["GCBFPLUS_TRAINING", "LEARNED_METHODS", "PRESETS", "method_group", "preset_fields"]

#: method name -> (group of the networks: "trivial" or "equivariant", the robot's group; reference controller)
LEARNED_METHODS: dict[str, tuple[str, str]] = {
    "gcbf": ("trivial", "nominal"),
    "gcbf+": ("trivial", "qp"),
    "egcbf": ("equivariant", "nominal"),
    "egcbf+": ("equivariant", "qp"),
}


def method_group(algo: str, robot: str = DEFAULT_ROBOT) -> str:
    """The config name of the networks' group of method ``algo`` for ``robot``: ``"trivial"`` or the robot's."""
    group = LEARNED_METHODS[algo][0]
    return make_robot(robot).group_name if group == "equivariant" else group


PRESETS = ("cpu", "paper-cpu", "paper-cpu-mlp", "cpu-torque", "paper", "tiny", "gcbfplus")

#: GCBF+'s training setting per benchmark robot (its pretrained models; docs/robots.md):
#: obstacles and arena side of its 8-agent training scenes
GCBFPLUS_TRAINING = {
    "single_integrator": (8, 4.0),
    "double_integrator": (8, 4.0),
    "dubins_car": (4, 4.0),
    "linear_drone": (8, 2.0),
}


def preset_fields(algo: str, name: str, robot: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """The :class:`~egcbf.nn.models.ModelConfig` and :class:`~egcbf.algo.config.TrainConfig` fields (two dicts; ``algo``
    and ``reference`` not among them) of method ``algo`` under preset ``name`` for ``robot``:

    * ``"cpu"``: the default CPU recipe on the acceleration command (ideal command model): 32 agents in arenas
      of side 1.6 / 2.0 / 2.5 m in turn, 4 obstacles; 4 environments x 128 steps per update, 192 graphs plus
      64 unsafe ones, 2 epochs of 8 minibatches of 32 graphs; a soft-min CBF head (``cbf_distance = 0.25``) on
      relative positions and velocities, the edge-sum policy head; learning rates 3e-4 (CBF) / 1e-3 (policy),
      the paper's loss constants, ``eta_c = 0.1`` for GCBF / EGCBF, 1 for GCBF+ / EGCBF+; validation on 4
      episodes of 64 agents at ``l = 2``; 60 minutes of wall time;
    * ``"paper-cpu"``: the paper's training regime (its Section V-C: 8 agents, ``l = 2``, 5 obstacles) with the
      ``cpu`` recipe's network, validated on that distribution (8 episodes), 30 minutes of wall time: the
      zero-shot setting of the paper's generalization claim (docs/equivariance.md);
    * ``"paper-cpu-mlp"``: the same with the paper's heads (MLP CBF and policy heads on the graph transformer,
      no closest-approach edge features);
    * ``"cpu-torque"``: the previous CPU recipe on body torque and thrust (8 agents, ``l = 2``, 5 obstacles;
      4 environments x 128 steps per update, 2 epochs of ~10 minibatches of 128 graphs; learning rates 3e-4
      (CBF) / 1e-4 (policy), the paper's loss constants; a CBF that reads neither the body rates nor the goal
      and is mirror-symmetric in z, residual scales of 0.25 on torque and 1 on thrust, ``eta_c = 0.1`` for
      GCBF / EGCBF, 1 for GCBF+ / EGCBF+; 60 minutes of wall time);
    * ``"paper"``: GCBF+'s CrazyFlie settings, which the paper says it follows (16 environments x 256-step
      episodes per update, buffers of 512 trajectories and 256 unsafe graphs, 8 epochs x 48 minibatches of
      256 graphs, 1000 updates, ``eta_c = 3e-5``) with the paper's ``gamma = 0.02``, ``eta_d = 0.2``,
      ``alpha = 1``; for a GPU;
    * ``"tiny"``: a seconds-long smoke configuration (tests).

    ``robot`` (:mod:`egcbf.robots`): a robot whose ``training_recipe`` is ``"paper"`` (the quadrotor: the recipes
    above) or another robot (the planar recipe,
    :func:`_planar_fields`: ``"cpu"``, ``"tiny"`` and, for GCBF+'s benchmark robots, ``"gcbfplus"``).
    """
    if algo not in LEARNED_METHODS:
        raise ValueError(f"unknown algo {algo!r}; choose one of {sorted(LEARNED_METHODS)}")
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {PRESETS}")
    _, reference = LEARNED_METHODS[algo]
    if make_robot(robot).training_recipe != "paper":  # (a clear error for an unknown robot)
        return _planar_fields(algo, name, robot)
    if name == "gcbfplus":
        raise ValueError(f"preset 'gcbfplus' is GCBF+'s setting for its benchmark robots {list(GCBFPLUS_TRAINING)}")
    model = {"group": method_group(algo, robot)}
    base: dict[str, Any] = {"num_threads": 1}  # small matrices: one thread is as fast, and never oversubscribes
    if name in ("cpu", "paper-cpu", "paper-cpu-mlp"):
        # the command interface (docs/learning.md, "Command interface"): the policy, the learned-CBF QP and the
        # loss act on a desired acceleration tracked by the attitude loop; the CBF reads relative positions and
        # velocities only (the states the ideal model moves); agents that sense nothing keep the nominal command
        model.update(
            interface="accel", cbf_body_rates=False, cbf_attitude=False, cbf_goal_edges=False,
            cbf_z_symmetric=False, accel_action_scale=1.0, policy_gate_isolated=True, edge_velocity=True,
            edge_closest_approach=True, cbf_head="edge_min", policy_head="edge_sum", cbf_distance=0.25,
        )  # fmt: skip
        # the policy head sums learned coefficients of each edge's geometric vectors (docs/learning.md, "The
        # policy's edge-sum head"); the CBF's prior barrier is 0 at a closest approach of 0.25 m (collision at
        # 0.1 m): the policy imitates the QP imperfectly, and a more cautious teacher was safer at N = 512
        # training covers the evaluation's densities (docs/learning.md, "Density"): 32 agents in arenas of side
        # 1.6 / 2.0 / 2.5 m in turn (7.8 / 4 / 2 agents per m^3; N = 512 at l = 4 is 8 per m^3), validation on
        # 64 agents at l = 2 (8 per m^3)
        base.update(
            num_agents=32, area_sizes=[1.6, 2.0, 2.5], num_obstacles=4, memory_trajectories=2,
            train_graphs=192, unsafe_samples=64, epochs=2, batch_size=32, lr_cbf=3e-4, lr_policy=1e-3,
            max_wall_minutes=60.0,
            eval_num_agents=64, eval_area_size=2.0, eval_num_obstacles=0, eval_episodes=4,
        )  # fmt: skip
        if reference == "nominal":
            base.update(eta_c=0.1)
    if name in ("paper-cpu", "paper-cpu-mlp"):
        # the paper's training distribution; validation on it (the run never sees the evaluation's densities)
        base.update(
            num_agents=8, area_size=2.0, area_sizes=None, num_obstacles=5, max_wall_minutes=30.0,
            eval_num_agents=8, eval_area_size=2.0, eval_num_obstacles=5, eval_episodes=8,
        )  # fmt: skip
        if name == "paper-cpu-mlp":
            model.update(cbf_head="mlp", policy_head="mlp", edge_closest_approach=False)
    if name == "cpu-torque":
        # the previous CPU recipe on body torque and thrust (kept for the interface comparison)
        # the CBF does not read the body rates and the torque residual is small (docs/learning.md, "cpu-torque
        # recipe"): with GCBF+'s choices (CBF on the full state, residual scale 2 on every channel) the QP and
        # the derivative term drive a state-independent torque bias that ruins goal reaching within 20 updates
        # (docs/learning.md, "cpu-torque recipe"); the CBF does not see the goal and the thrust residual scale is
        # 1 (from hover, enough to reach either end of the thrust range): a thrust bias of ~0.04 box from the
        # derivative term otherwise lowers every hover point below the reach radius
        # the CBF is mirror-symmetric in z (ModelConfig.cbf_z_symmetric): otherwise u_QP, which acts through thrust
        # only, pushes every approaching agent the same vertical way (u_QP - u_nom: -0.15 thrust box on average)
        model.update(
            cbf_body_rates=False, cbf_goal_edges=False, cbf_z_symmetric=True, torque_action_scale=0.25,
            action_scale=1.0,
        )  # fmt: skip
        # 20 gradient steps per update (the paper: 384) at the paper's 1e-4 / 1e-5 barely move the policy within
        # an hour (safe 84 -> 86 % in 90 updates); 3e-4 / 1e-4 gets there in 30 (docs/learning.md)
        base.update(lr_cbf=3e-4, lr_policy=1e-4, max_wall_minutes=60.0)
        if reference == "nominal":
            # with eta_c = 1 the pull to u_nom (which knows nothing of safety) outweighs the derivative term and
            # GCBF / EGCBF stay the nominal controller (reward -0.00, safe rate unchanged over 70 updates); the
            # + methods keep 1: u_QP carries the safety, and 0.1 lets the derivative term push a thrust bias
            base.update(eta_c=0.1)
    if name == "paper":
        model.update(hidden=128, head_hidden=256)
        base.update(
            rollout_envs=16, rollout_steps=256, buffer_trajectories=512, memory_trajectories=16,
            unsafe_buffer_size=256, unsafe_samples=16 * 256, epochs=8, batch_size=256, eta_c=3e-5,
            steps=1000, eval_interval=10, eval_episodes=32, checkpoint_interval=10, keep_checkpoints=0,
            device="cuda", num_threads=0,
        )  # fmt: skip
    elif name == "tiny":
        model.update(
            hidden=16, heads=2, head_hidden=16, interface="accel", cbf_attitude=False, cbf_body_rates=False,
            edge_velocity=True, edge_closest_approach=True, cbf_head="edge_min", policy_head="edge_sum",
        )  # fmt: skip
        base.update(
            num_agents=3, area_size=1.5, area_sizes=[1.5, 1.2], num_obstacles=1,
            env_overrides={"n_rays": 8, "lidar_max_hits": 4},
            rollout_envs=2, rollout_steps=12, horizon=4, buffer_trajectories=8, memory_trajectories=2,
            unsafe_buffer_size=16, unsafe_samples=8, epochs=1, batch_size=8, steps=4, eval_interval=2,
            eval_episodes=2, eval_max_steps=12, checkpoint_interval=2, lr_cbf=1e-3, lr_policy=1e-3,
        )  # fmt: skip
    return model, base


def _planar_fields(algo: str, name: str, robot: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """The planar recipe (``robot`` with a ``"control"`` interface, e.g. the unicycle): the networks act on
    the normalized raw control, the CBF has the closest-approach prior (``edge_min``) and reads relative
    positions and velocities, the policy's residual is a soft-min weighted sum over its closest edges
    (``edge_sum``, invariant coefficients): an MLP head imitated the learned-CBF QP too weakly (docs/robots.md,
    "Training the planar swarm"); 32 agents and 8 obstacles at 1-3.6 agents per m^2.

    ``"gcbfplus"`` (GCBF+'s benchmark robots): the same networks in GCBF+'s training setting (8 agents,
    its obstacles and arena, :data:`GCBFPLUS_TRAINING`), with the arena also 0.7x as wide every other update
    (twice the density: the reference table's densest 2-D cells), validated on 16 agents without obstacles in
    the training arena (a cell of the reference table), 30 CPU-minutes."""
    names = ("cpu", "tiny", "gcbfplus") if robot in GCBFPLUS_TRAINING else ("cpu", "tiny")
    if name not in names:
        raise ValueError(f"the {robot} has the presets {', '.join(repr(n) for n in names)}, not {name!r}")
    _, reference = LEARNED_METHODS[algo]
    model: dict[str, Any] = dict(
        group=method_group(algo, robot), robot=robot, interface="control", cbf_goal_edges=False,
        policy_gate_isolated=True, edge_velocity=True, edge_closest_approach=True, cbf_head="edge_min",
        cbf_distance=0.2, action_scale=1.0, policy_head="edge_sum", policy_free_distance=0.5,
    )  # fmt: skip
    # 32 agents and 8 obstacles in arenas of side 3 / 4 / 5.6 m in turn (3.6 / 2 / 1 agents per m^2; GCBF+
    # trains 8 agents and 8 obstacles at l = 4, 0.5 per m^2); validation on 64 agents and 8 obstacles at l = 8
    base: dict[str, Any] = dict(
        num_threads=1, num_agents=32, area_size=4.0, area_sizes=[3.0, 4.0, 5.6], num_obstacles=8,
        memory_trajectories=2, train_graphs=192, unsafe_samples=64, epochs=2, batch_size=32, lr_cbf=3e-4,
        lr_policy=1e-3, max_wall_minutes=30.0, eval_num_agents=64, eval_area_size=8.0, eval_num_obstacles=8,
        eval_episodes=4,
    )  # fmt: skip
    if reference == "nominal":
        base.update(eta_c=0.1)
    if name == "gcbfplus":
        # the residual spans the whole box from any nominal command, as GCBF+'s 2 pi + u_ref: with 1.0 a
        # double integrator at its speed clip, pushed on by the nominal, could barely brake; the CBF stays
        # within 5 cm of its closest-approach prior, which labels alone flatten (docs/robots.md)
        model.update(action_scale=2.0, cbf_correction_bound=0.05)
        obstacles, side = GCBFPLUS_TRAINING[robot]
        # class-K slope 10 / s in the QP and the derivative loss: with 0.1-1 the untrained CBF's QP let a
        # negative h recover too slowly to stop a 1.4 m/s approach (65 % safe vs 100 % at 16 agents, l = 4)
        base.update(alpha=10.0, qp_alpha=10.0, straight_through_clip=True)
        base.update(
            num_agents=8, area_size=side, area_sizes=[round(0.7 * side, 3), side], num_obstacles=obstacles,
            eval_num_agents=16, eval_area_size=side, eval_num_obstacles=0, max_wall_minutes=None,
            max_cpu_minutes=30.0,
        )  # fmt: skip
    if name == "tiny":
        model.update(hidden=16, heads=2, head_hidden=16)
        base.update(
            num_agents=3, area_size=1.0, area_sizes=[1.0, 0.8], num_obstacles=1,
            env_overrides={"n_rays": 8, "lidar_max_hits": 4},
            rollout_envs=2, rollout_steps=12, horizon=4, buffer_trajectories=8, memory_trajectories=2,
            unsafe_buffer_size=16, unsafe_samples=8, epochs=1, batch_size=8, steps=4, eval_interval=2,
            eval_episodes=2, eval_num_agents=None, eval_area_size=None, eval_max_steps=12,
            checkpoint_interval=2, lr_cbf=1e-3, lr_policy=1e-3, train_graphs=None,
        )  # fmt: skip
    return model, base
