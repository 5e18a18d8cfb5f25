"""What the validation-episode diagnostics (``cbf_teacher.py``, ``collision_anatomy.py``) share: the scene's
command-line arguments and the JSON record ``--out`` writes (the command, the scene and the results).

Validation episodes use seed 777 by default: disjoint from training, selection and the evaluation seeds of
``egcbf eval`` / ``egcbf reproduce``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

SCENE = ("checkpoint", "num_agents", "area", "episodes", "seed")


def add_scene_arguments(ap: argparse.ArgumentParser, num_agents: int, area: float, episodes: int) -> None:
    """``--checkpoint``, ``--num-agents``, ``--area``, ``--episodes``, ``--seed`` (777) and ``--out``."""
    ap.add_argument("--checkpoint", default="checkpoints/egcbf+")
    ap.add_argument("--num-agents", type=int, default=num_agents)
    ap.add_argument("--area", type=float, default=area)
    ap.add_argument("--episodes", type=int, default=episodes)
    ap.add_argument("--seed", type=int, default=777)
    ap.add_argument("--out", type=Path, default=None, help="also write the results to this JSON file")


def write_record(args: argparse.Namespace, **results) -> None:
    """Write ``{"command", the scene's arguments, **results}`` to ``args.out`` (nothing without ``--out``)."""
    if args.out is None:
        return
    args.out.parent.mkdir(parents=True, exist_ok=True)
    record = {"command": "python " + " ".join(sys.argv), **{k: getattr(args, k) for k in SCENE}, **results}
    args.out.write_text(json.dumps(record, indent=2) + "\n")
