"""Which model should the learned-CBF QP use for ``Lg h`` over acceleration commands: measured on a trained CBF.

For the CBF of a checkpoint and states from rollouts of its own policy in a dense training scene (32 agents,
l = 1.6 m), both models of :class:`egcbf.algo.interface.AccelInterface` give ``Lg h`` ``(B, N, N, 3)``:

* ``ideal``: the double integrator the command defines (``Lg_j h = A dh/dv_j``);
* ``closed_loop``: one 25 ms step through the attitude loop and the rigid body, linearized at the nominal command.

Reported: the mean horizontal and vertical size of each agent's own ``Lg_i h_i`` (in the agent's yaw frame), and
for the QP target of each model the mean horizontal and vertical size of its correction ``c_QP - c_nom`` over the
agents it moves; the ratio horizontal / vertical says where the QP would steer.

    python benchmarks/command_models.py --checkpoint checkpoints/egcbf+
"""

from __future__ import annotations

import argparse
import dataclasses

import torch

from egcbf.algo.interface import AccelInterface, solve_command_qp
from egcbf.io.report import replace_section
from egcbf.train.checkpoint import load_learner


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default="checkpoints/egcbf+")
    ap.add_argument("--seed", type=int, default=4242)
    ap.add_argument("--graphs", type=int, default=64, help="states sampled from the rollout")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    learner = load_learner(args.checkpoint)
    if learner.config.model.interface != "accel":
        raise SystemExit("the checkpoint does not use the acceleration interface")
    learner.config = dataclasses.replace(learner.config, area_sizes=[1.6])
    rollout = learner.collect(args.seed).flatten()
    data = rollout[torch.randperm(len(rollout), generator=torch.Generator().manual_seed(args.seed))[: args.graphs]]
    graph = data.graph(learner.env_config)
    lines = [
        f"`python benchmarks/command_models.py --checkpoint {args.checkpoint}` ({args.graphs} states of a 32-agent, "
        "l = 1.6 m rollout of the checkpoint's policy; accelerations in units of 5 m/s^2, agent's yaw frame).",
        "",
        "| model | own Lg h: horizontal | vertical | QP correction: horizontal | vertical | horizontal / vertical |",
        "|---|---|---|---|---|---|",
    ]
    for model in ("ideal", "closed_loop"):
        itf = AccelInterface(params=learner.params, model=model)
        c_nom = itf.nominal(data.x, data.goals)
        _, _, lg = itf.lie_derivatives(learner.cbf_target, graph, data.x, learner.env_config, c_nom)
        lg_local = itf.to_local(data.x[:, None].to(lg.dtype), lg)
        own = torch.diagonal(lg_local, dim1=1, dim2=2).transpose(1, 2)  # (B, N, 3): dh_i / dc_i
        c_qp, _ = solve_command_qp(itf, learner.cbf_target, graph, data.x, c_nom, learner.env_config,
                                   alpha=learner.config.qp_alpha)  # fmt: skip
        corr = itf.to_local(data.x, c_qp - c_nom).double()  # c_nom is inside the box already (clipped)
        moved = corr.norm(dim=-1) > 1e-4
        ch, cv = corr[..., :2].norm(dim=-1)[moved].mean(), corr[..., 2].abs()[moved].mean()
        lines.append(
            f"| {model} | {own[..., :2].norm(dim=-1).mean():.3g} | {own[..., 2].abs().mean():.3g} | "
            f"{ch:.3g} | {cv:.3g} | {ch / cv:.2f} |"
        )
    body = "\n".join(lines)
    print(body)
    if not args.no_write:
        replace_section("docs/learning.md", "command-models", body)


if __name__ == "__main__":
    main()
