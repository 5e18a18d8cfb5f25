"""How fast can a policy head learn its teacher? Offline imitation of the learned-CBF QP on fixed data.

The + methods train the policy towards ``u_QP``, the learned-CBF QP's command. This script isolates that part of
learning: it collects rollouts of an untrained policy (what the first updates of a run see) in the training
scenes of a checkpoint's config, computes the QP targets once with the checkpoint's target CBF, and fits fresh
policies with each policy head on the control loss alone (Adam, the config's learning rate and minibatch size).
It reports, on held-out graphs, the error ``|c_pi - c_QP|`` on the agents the QP corrects by more than 0.1
(normalized command units, 0.5 m/s^2), against the error of the nominal command (``c_pi = c_nom``).

    python benchmarks/policy_imitation.py --checkpoint checkpoints/egcbf+ --steps 300
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import torch

from egcbf.algo.buffer import Samples
from egcbf.algo.learner import policy_command
from egcbf.nn import PolicyNet
from egcbf.train.checkpoint import load_learner


def corrected_error(policy, model_cfg, itf, data: Samples, u_ref, env_cfg, threshold: float) -> tuple[float, float]:
    """Mean ``|c_pi - c_QP|`` over agents the QP corrects by more than ``threshold``, and of the nominal."""
    with torch.no_grad():
        c, c_nom = policy_command(policy, model_cfg, itf, data.graph(env_cfg), data.x, data.goals)
    moved = (u_ref - c_nom).norm(dim=-1) > threshold
    return float((c - u_ref).norm(dim=-1)[moved].mean()), float((c_nom - u_ref).norm(dim=-1)[moved].mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default="checkpoints/egcbf+")
    ap.add_argument("--heads", default="mlp,edge_sum")
    ap.add_argument("--rollouts", type=int, default=3, help="rollouts (each rollout_envs x rollout_steps graphs)")
    ap.add_argument("--train-graphs", type=int, default=768)
    ap.add_argument("--test-graphs", type=int, default=256)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--report", type=int, default=50)
    ap.add_argument("--threshold", type=float, default=0.1)
    ap.add_argument("--lr", type=float, default=None)
    ap.add_argument("--seed", type=int, default=4242)
    args = ap.parse_args()
    torch.set_num_threads(1)
    learner = load_learner(args.checkpoint)
    cfg, env_cfg, itf = learner.config, learner.env_config, learner.interface
    torch.manual_seed(args.seed)
    learner.policy = PolicyNet(cfg.model).to(learner.device, learner.dtype)  # untrained: the early runs' data
    rollouts = []
    for k in range(args.rollouts):
        learner.step = k  # cycles the arena sizes as training does
        rollouts.append(learner.collect(args.seed + k).flatten())
    data = Samples.cat(rollouts)
    perm = torch.randperm(len(data), generator=torch.Generator().manual_seed(args.seed))
    train, test = data[perm[: args.train_graphs]], data[perm[args.train_graphs : args.train_graphs + args.test_graphs]]
    u_train, _ = learner.reference(train)
    u_test, _ = learner.reference(test)
    lr = args.lr or cfg.lr_policy
    print(f"{args.checkpoint}: {len(train)} train / {len(test)} test graphs of {cfg.num_agents} agents, lr {lr}")
    for head in args.heads.split(","):
        model = dataclasses.replace(cfg.model, policy_head=head)
        torch.manual_seed(args.seed)
        policy = PolicyNet(model).to(learner.device, learner.dtype)
        opt = torch.optim.Adam(policy.parameters(), lr=lr)
        gen = torch.Generator().manual_seed(args.seed)
        err, nominal = corrected_error(policy, model, itf, test, u_test, env_cfg, args.threshold)
        print(f"  {head:9s} step    0: error {err:.3f} (nominal {nominal:.3f})", flush=True)
        t0 = time.perf_counter()
        for step in range(1, args.steps + 1):
            idx = torch.randint(len(train), (cfg.batch_size,), generator=gen)
            batch = train[idx]
            c, _ = policy_command(policy, model, itf, batch.graph(env_cfg), batch.x, batch.goals)
            loss = (c - u_train[idx]).square().sum(-1).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if step % args.report == 0:
                err, _ = corrected_error(policy, model, itf, test, u_test, env_cfg, args.threshold)
                ms = 1e3 * (time.perf_counter() - t0) / step
                print(f"  {head:9s} step {step:4d}: error {err:.3f}  ({ms:.0f} ms/step)", flush=True)


if __name__ == "__main__":
    main()
