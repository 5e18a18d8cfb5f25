"""Regenerate the teacher measurements and the large-arena fine-tuning results (figure and the "finetune" section of
docs/learning.md).

Reads:

* ``docs/results/finetune/teachers/*.json``: ``python benchmarks/cbf_teacher.py ... --out`` (each file holds its
  command): the policy and the teacher candidates of a checkpoint run as controllers on validation episodes;
* ``docs/results/finetune/<attempt>/<algo>-s<k>/``: one fine-tuning run per training seed ``k`` (``egcbf train
  --init-from``): its ``config.json``, ``metrics.csv`` (validation on 2 episodes of 512 agents at l = 4 from the
  run's own seed ``k + 1000``) and ``best_state.json`` (the update ``best/`` holds), and optionally the ``egcbf eval``
  outputs ``eval-*/`` (``metrics.json``, ``run.json``) of the selected checkpoint. For evaluations on the shipped
  policies' settings (evaluation seed 0, 50 episodes, N = 512, l = 4), the shipped policies' cells of
  ``docs/results/paper-target/`` (the reproduction's cells of the policies they started from, docs/paper_target.md)
  are the "before" column.

Run: .venv/bin/python docs/gen_finetune.py
"""

import csv
import json
import statistics
from pathlib import Path

from egcbf.io.report import replace_section
from egcbf.viz.curves import training_curves

ROOT = Path(__file__).parent
RESULTS = ROOT / "results" / "finetune"
#: the cells of the policies the fine-tuning started from (docs/paper_target.md), the "before" column
REPRODUCTION = ROOT / "results" / "paper-target"
FIG = ROOT / "figures" / "finetune.png"
ALGO_NAMES = {"egcbf+": "EGCBF+", "gcbf+": "GCBF+"}
TARGETS = {"cbf": "soft-min QP target (paper)", "edges": "per-edge QP target"}


def _reproduction_cell(algo: str, seed: int, obstacles: int, n: int) -> dict | None:
    name = algo if seed == 0 else f"{algo}-s{seed}"
    path = REPRODUCTION / f"{name}_obs{obstacles}" / f"N{n}.json"
    return json.loads(path.read_text()) if path.exists() else None


def _spread(values: list[float]) -> str:
    if len(values) < 2:
        return f"{values[0]:.1f}" if values else "-"
    return f"{statistics.mean(values):.1f} ({min(values):.1f}-{max(values):.1f})"


def _validation(run: Path) -> list[tuple[int, float]]:
    with open(run / "metrics.csv", newline="") as f:
        return [(int(r["step"]), 100 * float(r["safe_rate"])) for r in csv.DictReader(f)]


def _teachers() -> list[str]:
    files = sorted((RESULTS / "teachers").glob("*.json"))
    if not files:
        return []
    lines = [
        "| checkpoint | scene (validation seed) | controller | safe % | reach % |",
        "|---|---|---|---|---|",
    ]
    for path in files:
        d = json.loads(path.read_text())
        scene = f"N = {d['num_agents']}, l = {d['area']:g}, {d['episodes']} ep. (seed {d['seed']})"
        for r in d["rows"]:
            lines.append(
                f"| `{d['checkpoint']}` | {scene} | {r['teacher']} | {100 * r['safe_rate']:.1f} | "
                f"{100 * r['reach_rate']:.1f} |"
            )
    commands = "\n".join(f"    {json.loads(p.read_text())['command']}" for p in files)
    return ["Commands:", "", commands, "", *lines, ""]


def _anatomy() -> list[str]:
    files = sorted((RESULTS / "anatomy").glob("*.json"))
    lines = []
    for path in files:
        d = json.loads(path.read_text())
        lines += [f"    {d['command']}", "", f"{d['contacts']} new contacts. Min, quartiles and max:", "",
                  "| quantity | min | q1 | median | q3 | max |", "|---|---|---|---|---|---|"]  # fmt: skip
        names = {"step": "step (of 256)", "closing": "closing speed (m/s)", "speed_fast": "faster agent's speed (m/s)",
                 "speed_slow": "slower agent's speed (m/s)", "goal_near": "nearer goal distance (m)",
                 "goal_far": "farther goal distance (m)"}  # fmt: skip
        for key, q in d["min_q1_q2_q3_max"].items():
            lines.append(f"| {names.get(key, key)} | " + " | ".join(f"{v:.2f}" for v in q) + " |")
        lines.append("")
    return lines


def main() -> None:
    found = sorted(RESULTS.iterdir()) if RESULTS.exists() else []
    attempts = [d for d in found if d.is_dir() and d.name not in ("teachers", "anatomy")]
    runs = {a: sorted(r for r in a.iterdir() if (r / "metrics.csv").exists()) for a in attempts}
    runs = {a: rs for a, rs in runs.items() if rs}
    if not runs:
        raise SystemExit(f"no fine-tuning runs under {RESULTS}")
    labels: dict[str, list[Path]] = {}  # one curve per method and target, over its seeds
    for rs in runs.values():
        for run in rs:
            cfg = json.loads((run / "config.json").read_text())
            algo = ALGO_NAMES.get(cfg["algo"], cfg["algo"])
            labels.setdefault(f"{algo}, {TARGETS[cfg.get('qp_constraints', 'cbf')]}", []).append(run)
    training_curves(
        labels,
        FIG,
        title="Fine-tuning in large arenas: validation, 2 episodes x 512 agents at l = 4",
    )
    table = [
        "| attempt, method | training seed | validation safe %: update 0 -> best (update) -> last (update) | "
        "evaluation | safe % before | safe % after | success % after |",
        "|---|---|---|---|---|---|---|",
    ]
    summary: dict[tuple[str, str, str], tuple[list[float], list[float]]] = {}
    for attempt, rs in runs.items():
        for run in rs:
            cfg = json.loads((run / "config.json").read_text())
            seed, algo = int(cfg["seed"]), cfg["algo"]
            who = f"`{attempt.name}`, {ALGO_NAMES.get(algo, algo)}"
            curve = _validation(run)
            best = (
                json.loads((run / "best_state.json").read_text())["step"]
                if (run / "best_state.json").exists()
                else None
            )
            best_safe = dict(curve).get(best)
            val = (
                f"{curve[0][1]:.1f} -> {best_safe:.1f} ({best}) -> {curve[-1][1]:.1f} ({curve[-1][0]})"
                if best_safe is not None
                else f"{curve[0][1]:.1f} -> {curve[-1][1]:.1f} ({curve[-1][0]})"
            )
            evals = sorted(e for e in run.glob("eval-*") if (e / "metrics.json").exists())  # finished ones
            if not evals:
                table.append(f"| {who} | {seed} | {val} | not run | | | |")
            for ev in evals:
                meta = json.loads((ev / "run.json").read_text())
                row = json.loads((ev / "metrics.json").read_text())[0]
                n, obstacles = row["num_agents"], int(meta["obstacles"])
                before = _reproduction_cell(algo, seed, obstacles, n)
                same = (
                    before is not None
                    and before["key"]["seed"] == meta["seed"]
                    and before["key"]["episodes"] == meta["episodes"]
                    and float(before["key"]["area"] or meta["area"]) == float(meta["area"])
                )
                b = 100 * before["row"]["safe_rate"] if same else None
                a = 100 * row["safe_rate"]
                what = (
                    f"N = {n}, l = {meta['area']:g}, {obstacles} obstacles, seed {meta['seed']}, {meta['episodes']} ep."
                )
                table.append(
                    f"| {who} | {seed} | {val} | {what} | {'-' if b is None else f'{b:.1f}'} | {a:.1f} | "
                    f"{100 * row['success_rate']:.1f} |"
                )
                if b is not None:
                    s = summary.setdefault((who, algo, what), ([], []))
                    s[0].append(b)
                    s[1].append(a)
    for (who, _, what), (before, after) in summary.items():
        table.append(
            f"| **{who}, mean (min-max) over {len(after)} seeds** | | | {what} | {_spread(before)} | "
            f"**{_spread(after)}** | |"
        )
    body = "\n".join(
        [
            "Generated by `.venv/bin/python docs/gen_finetune.py` from `docs/results/finetune/` (and, for the column "
            "before, the cells of the policies they started from, `docs/results/paper-target/`, docs/paper_target.md).",
            "",
            "**Where the shipped policy collides** (`benchmarks/collision_anatomy.py`):",
            "",
            *_anatomy(),
            "**Teachers as controllers** (`benchmarks/cbf_teacher.py`: the policy, the soft-min QP target with the "
            "checkpoint's target CBF at several alphas, the prior's QP, and the nominal command behind the per-edge "
            "QPs):",
            "",
            *_teachers(),
            "**Fine-tuning runs** (warm start from the shipped checkpoint of each seed):",
            "",
            f"![fine-tuning curves](figures/{FIG.name})",
            "",
            *table,
            "",
        ]
    )
    replace_section(ROOT / "learning.md", "finetune", body, heading="#### Fine-tuning in large arenas (measured)")
    print(f"wrote {FIG} and the 'finetune' section of {ROOT / 'learning.md'}")


if __name__ == "__main__":
    main()
