"""How safe is the teacher? The learned-CBF QP of a checkpoint run as a controller, beside the checkpoint's policy.

The + methods train the policy to imitate ``u_QP``, the centralized QP over commands with the learned (target) CBF
(:mod:`egcbf.algo.qp`). If that QP, used directly as a controller, is no safer than the nominal controller, the
policy cannot learn safety from it. This script measures, on validation episodes (seed 777 by default, disjoint
from training, selection and the evaluation seeds of ``egcbf eval`` / ``egcbf reproduce``):

* ``policy``: the checkpoint's policy (what ``egcbf eval`` runs);
* ``teacher``: the learned-CBF QP with the checkpoint's target CBF, the QP's ``alpha`` of its config;
* ``prior`` (``--prior``): the same QP on the untrained soft-min CBF head (closest-approach distance minus the
  checkpoint's ``cbf_distance``), which tells the learned teacher apart from the QP machinery;
* ``--edge-teachers``: the nominal command behind the per-agent, per-edge QPs of :mod:`egcbf.algo.edge_qp` (the
  target of ``qp_constraints = "edges"``): ``edges-cbf`` (the checkpoint's target CBF's edge barriers, the QP
  target's alpha ``qp_edge_alpha``), ``edges-prior`` (the untrained prior's) and ``dcbf`` (the hand-crafted
  braking-distance rows of the ``dcbf`` filter), each as a controller.

For a checkpoint of a robot driven through its raw control (GCBF+'s benchmark robots) the teachers are
:func:`egcbf.algo.edge_qp.edge_qp_controls` around the nominal control: ``edges-cbf a=<alpha>`` for each of
``--edge-alphas`` (default: the config's ``qp_edge_alpha``) and ``edges-prior`` (with ``--prior``), with the rows'
``--min-authority`` (default: the config's); ``--obstacles`` and ``--max-steps`` set the scene.

``--out FILE.json`` also writes the rows (with the command) for the docs.

    python benchmarks/cbf_teacher.py --checkpoint checkpoints/egcbf+ --num-agents 64 --area 2 --episodes 2 --prior
    python benchmarks/cbf_teacher.py --num-agents 128 --area 2.5 --alphas 0.1,1,3 --prior --edge-teachers
    python benchmarks/cbf_teacher.py --checkpoint checkpoints/double_integrator/gcbf+ --num-agents 256 --area 16 \
        --episodes 1 --max-steps 1024 --obstacles 32 --edge-alphas 10,30,100 --prior
"""

from __future__ import annotations

import argparse
import dataclasses

import torch
from validation_scene import add_scene_arguments, write_record

from egcbf.algo.edge_qp import edge_qp_controls
from egcbf.algo.interface import solve_command_qp
from egcbf.control.filters import FilterConfig, FilteredController
from egcbf.env.graph import build_graph
from egcbf.evaluate.episodes import evaluate
from egcbf.nn import CBFNet
from egcbf.train.checkpoint import load_learner


class EdgeTeacher:
    """``u, info = ctrl(state, env_config)``: the nominal control behind every agent's per-edge QP, for robots driven
    through their raw control (:func:`egcbf.algo.edge_qp.edge_qp_controls`); ``cbf`` ``None``: the prior's rows."""

    def __init__(self, cbf, model, interface, alpha: float, min_authority: float):
        self.cbf, self.model, self.itf = cbf, model, interface
        self.alpha, self.min_authority = alpha, min_authority

    @torch.no_grad()
    def __call__(self, state, env_config):
        graph = build_graph(state, env_config)  # casts the LiDAR
        c, _ = edge_qp_controls(
            graph, state.x, self.itf, self.itf.nominal(state.x, state.goals), alpha=self.alpha, margin=0.0,
            cbf=self.cbf, distance=self.model.cbf_distance, horizon=self.model.closest_approach_horizon,
            min_authority=self.min_authority,
        )  # fmt: skip
        return self.itf.apply(state.x, c.to(state.x)), {}


class LearnedCBFQP:
    """``u, info = ctrl(state, env_config)``: the learned-CBF QP over the interface's commands, tracked."""

    def __init__(self, cbf, interface, alpha: float):
        self.cbf, self.itf, self.alpha = cbf, interface, alpha

    @torch.no_grad()
    def __call__(self, state, env_config):
        p = next(self.cbf.parameters())
        s = state.to(p.device, dtype=p.dtype)
        graph = build_graph(s, env_config)
        c, _ = solve_command_qp(self.itf, self.cbf, graph, s.x, self.itf.nominal(s.x, s.goals), env_config,
                                alpha=self.alpha)  # fmt: skip
        return self.itf.apply(s.x, c).to(state.x), {}


def acceleration_teachers(learner, args) -> dict:
    """The quadrotor's controllers of the module doc, by name."""
    cfg = learner.config
    alphas = [float(a) for a in args.alphas.split(",")] if args.alphas else [cfg.qp_alpha]
    ctrls = {"policy": lambda c: learner.controller()}
    for a in alphas:
        name = "teacher" if args.alphas is None else f"teacher a={a:g}"
        ctrls[name] = lambda c, a=a: LearnedCBFQP(learner.cbf_target, learner.interface, a)
    if args.prior:
        torch.manual_seed(0)
        prior = CBFNet(dataclasses.replace(cfg.model, cbf_head="edge_min"))
        ctrls["prior"] = lambda c: LearnedCBFQP(prior, learner.interface, cfg.qp_alpha)
    if args.edge_teachers:
        edge = FilterConfig(kind="cbf", alpha=cfg.qp_edge_alpha)
        ctrls["edges-cbf"] = lambda c: FilteredController(None, cfg.model, edge, learner.cbf_target)
        ctrls["edges-prior"] = lambda c: FilteredController(None, cfg.model, dataclasses.replace(edge, kind="prior"))
        ctrls["dcbf"] = lambda c: FilteredController(None, cfg.model, FilterConfig.for_kind("dcbf"))
    return ctrls


def raw_control_teachers(learner, args) -> dict:
    """The policy and the per-edge teachers of a control-interface checkpoint (module doc), by name."""
    cfg = learner.config
    ctrls = {"policy": lambda c: learner.controller()}
    alphas = [float(a) for a in args.edge_alphas.split(",")] if args.edge_alphas else [cfg.qp_edge_alpha]
    least = cfg.qp_edge_min_authority if args.min_authority is None else args.min_authority
    for a in alphas:
        ctrls[f"edges-cbf a={a:g}"] = lambda c, a=a: EdgeTeacher(learner.cbf_target, cfg.model, learner.interface, a,
                                                                  least)  # fmt: skip
    if args.prior:
        ctrls["edges-prior"] = lambda c: EdgeTeacher(None, cfg.model, learner.interface, alphas[-1], least)
    return ctrls


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(ap, num_agents=64, area=2.0, episodes=2)
    ap.add_argument("--prior", action="store_true", help="also the QP on the untrained soft-min head")
    ap.add_argument("--alphas", default=None, help="comma-separated QP alphas for the teacher (default: the config's)")
    ap.add_argument("--edge-teachers", action="store_true", help="also the nominal command behind per-edge QPs")
    ap.add_argument("--only", default=None, help="comma-separated controller names to run (default: all selected)")
    ap.add_argument("--obstacles", type=int, default=0, help="obstacles per scene")
    ap.add_argument("--max-steps", type=int, default=None, help="episode length (default: the robot's)")
    ap.add_argument("--edge-alphas", default=None, help="control-interface robots: comma-separated per-edge alphas")
    ap.add_argument("--min-authority", type=float, default=None, help="the per-edge rows' qp_edge_min_authority")
    args = ap.parse_args()
    torch.set_num_threads(1)
    learner = load_learner(args.checkpoint)
    cfg = learner.config
    if cfg.model.interface == "control":
        ctrls = raw_control_teachers(learner, args)
    elif cfg.model.interface == "accel":
        ctrls = acceleration_teachers(learner, args)
    else:
        raise SystemExit("the teacher check needs a checkpoint on the acceleration or the control interface")
    if args.only:
        keep = args.only.split(",")
        unknown = sorted(set(keep) - set(ctrls))
        if unknown:
            raise SystemExit(f"--only names {unknown}; the controllers are {sorted(ctrls)}")
        ctrls = {k: v for k, v in ctrls.items() if k in keep}
    print(f"{args.checkpoint}: {args.episodes} episodes, N = {args.num_agents}, l = {args.area}, seed {args.seed}")
    results = []
    for name, make in ctrls.items():
        rows, _ = evaluate(make, [args.num_agents], area_size=args.area, episodes=args.episodes, seed=args.seed,
                           show_progress=False, env_overrides=cfg.env_overrides or None, robot=cfg.model.robot,
                           num_obstacles=args.obstacles, max_steps=args.max_steps)  # fmt: skip
        r = rows[0]
        print(f"  {name:14s} safe {100 * r['safe_rate']:5.1f} %  reach {100 * r['reach_rate']:5.1f} %", flush=True)
        results.append({"teacher": name, **{k: r[k] for k in ("safe_rate", "reach_rate", "success_rate")}})
    write_record(args, rows=results)


if __name__ == "__main__":
    main()
