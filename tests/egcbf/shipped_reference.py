"""Reference outputs of the shipped EGCBF+ and GCBF+ on a fixed scene, for the regression test in test_shipped.py.

Speed-ups and refactors must not change what a trained network computes. This records, in float64, the policy
residual, the CBF value and the applied control of each checkpoint of ``METHODS`` (``checkpoints/egcbf+``,
``checkpoints/gcbf+``, and the two policies each is the weight average of: the fine-tuned one and the one trained
with the paper's QP target it started from) on one fixed
scene (32 agents, 3 obstacles, after 5 steps of the nominal controller), with the sha256 of each checkpoint's
weights (the tensors, not the file: the checkpoint format's header may change while the weights do not), into
``tests/egcbf/data/shipped_reference.json``. Regenerate it only when a checkpoint is replaced or added (the test
says so when the hash differs); entries whose checkpoint is unchanged keep their recorded outputs, so regenerating
never makes a code change pass for them:

    python tests/egcbf/shipped_reference.py
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import torch

from egcbf.env import EnvConfig, SwarmEnv
from egcbf.env.graph import build_graph
from egcbf.robots.quadrotor.nominal import nominal_control
from egcbf.train.checkpoint import load_learner

ROOT = Path(__file__).resolve().parents[2]
DATA = Path(__file__).resolve().parent / "data" / "shipped_reference.json"
#: checkpoint directories under checkpoints/
METHODS = ("egcbf+", "gcbf+", "fine-tuned/egcbf+", "fine-tuned/gcbf+", "paper-target/egcbf+", "paper-target/gcbf+")


def checkpoint_hash(method: str) -> str:
    """SHA-256 of the checkpoint's tensors: names, dtypes, shapes and bytes, in name order."""
    from safetensors.torch import load_file

    h = hashlib.sha256()
    for name, t in sorted(load_file(str(ROOT / "checkpoints" / method / "model.safetensors")).items()):
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.contiguous().view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


@torch.no_grad()
def outputs(method: str) -> dict[str, list]:
    """``pi`` (policy residual, world frame), ``h`` (CBF) and ``u`` (applied control) on the fixed scene, float64."""
    learner = load_learner(ROOT / "checkpoints" / method)
    learner.policy.double()
    learner.cbf.double()
    cfg = EnvConfig(num_agents=32, area_size=2.0, num_obstacles=3, num_envs=1)
    env = SwarmEnv(cfg, dtype=torch.float64)
    state = env.reset(7)
    for _ in range(5):
        state, _ = env.step(state, nominal_control(state.x, state.goals, cfg.params))
    graph = build_graph(state, cfg)
    u, _ = learner.controller()(state, cfg)
    return {
        "pi": learner.policy(graph).tolist(),
        "h": learner.cbf(graph).tolist(),
        "u": u.reshape(-1, u.shape[-1]).tolist(),
    }


def main() -> None:
    old = json.loads(DATA.read_text()) if DATA.exists() else {}
    data = {}
    for m in METHODS:
        sha = checkpoint_hash(m)
        kept = old.get(m, {}).get("sha256") == sha
        data[m] = old[m] if kept else {"sha256": sha, **outputs(m)}
        print(f"{m}: {'kept' if kept else 'recorded'}")
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps(data) + "\n")
    print(f"wrote {DATA}")


if __name__ == "__main__":
    main()
