"""How safe is the teacher? The learned-CBF QP of a checkpoint run as a controller, beside the checkpoint's policy.

The + methods train the policy to imitate ``u_QP``, the centralized QP over commands with the learned (target) CBF
(:mod:`egcbf.algo.qp`). If that QP, used directly as a controller, is no safer than the nominal controller, the
policy cannot learn safety from it. This script measures, on validation episodes (seed 777 by default, disjoint
from training, selection and the evaluation seeds of ``egcbf eval`` / ``egcbf reproduce``):

* ``policy``: the checkpoint's policy (what ``egcbf eval`` runs);
* ``teacher``: the learned-CBF QP with the checkpoint's target CBF, the QP's ``alpha`` of its config;
* ``prior`` (``--prior``): the same QP on the untrained soft-min CBF head (closest-approach distance minus 0.15 m),
  which tells the learned teacher apart from the QP machinery.

    python benchmarks/cbf_teacher.py --checkpoint checkpoints/egcbf+ --num-agents 64 --area 2 --episodes 2 --prior
"""

from __future__ import annotations

import argparse
import dataclasses

import torch

from egcbf.algo.interface import solve_command_qp
from egcbf.checkpoint import load_learner
from egcbf.evaluate import evaluate
from egcbf.graph import build_graph
from egcbf.nn import CBFNet


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default="checkpoints/egcbf+")
    ap.add_argument("--num-agents", type=int, default=64)
    ap.add_argument("--area", type=float, default=2.0)
    ap.add_argument("--episodes", type=int, default=2)
    ap.add_argument("--seed", type=int, default=777)
    ap.add_argument("--prior", action="store_true", help="also the QP on the untrained soft-min head")
    args = ap.parse_args()
    torch.set_num_threads(1)
    learner = load_learner(args.checkpoint)
    cfg = learner.config
    if cfg.model.interface != "accel":
        raise SystemExit("the teacher check needs a checkpoint on the acceleration interface")
    ctrls = {"policy": lambda c: learner.controller(),
             "teacher": lambda c: LearnedCBFQP(learner.cbf_target, learner.interface, cfg.qp_alpha)}  # fmt: skip
    if args.prior:
        torch.manual_seed(0)
        prior = CBFNet(dataclasses.replace(cfg.model, cbf_head="edge_min"))
        ctrls["prior"] = lambda c: LearnedCBFQP(prior, learner.interface, cfg.qp_alpha)
    print(f"{args.checkpoint}: {args.episodes} episodes, N = {args.num_agents}, l = {args.area}, seed {args.seed}")
    for name, make in ctrls.items():
        rows, _ = evaluate(make, [args.num_agents], area_size=args.area, episodes=args.episodes, seed=args.seed,
                           show_progress=False, env_overrides=cfg.env_overrides or None)  # fmt: skip
        r = rows[0]
        print(f"  {name:8s} safe {100 * r['safe_rate']:5.1f} %  reach {100 * r['reach_rate']:5.1f} %")


if __name__ == "__main__":
    main()
