"""Regenerate the results tables of docs/safety_filters.md from docs/results/filters/.

Each ``docs/results/filters/<split>/<row>/<case>/`` is the output of one ``egcbf eval`` (``metrics.json``: one row
per swarm size; ``run.json``: the exact command, checkpoint, filter, seed, episodes, machine). ``<split>`` is
``evaluation`` (seed 0, Table I's seed, never used for a choice; the settings were chosen on seed 777). ``<row>``
names the controller (``egcbf+-s0-dcbf``: the shipped EGCBF+ seed 0 behind the ``dcbf`` filter), ``<case>`` the
arena and obstacles. Each cell is shown beside the reproduction's cells of the same N, arena, obstacles and seed.

To add a cell: ``egcbf eval --checkpoint checkpoints/egcbf+ --filter dcbf --num-agents 512 --area 4 --obstacles 0
--episodes 50 --seed 0 --out docs/results/filters/evaluation/egcbf+-s0-dcbf/l4``, then run:

    .venv/bin/python docs/gen_filters.py
"""

import json
import re
from pathlib import Path

from egcbf.evaluate.bootstrap import mean_ci
from egcbf.io.report import pct, replace_section

ROOT = Path(__file__).parent
RESULTS = ROOT / "results" / "filters"
REPRODUCTION = ROOT / "results" / "reproduction"
PAPER_TARGET = ROOT / "results" / "paper-target"
DOC = ROOT / "safety_filters.md"
#: the reproduction's controllers shown beside the filtered ones: (label, cell folder, runs averaged). The filtered
#: evaluations of docs/results/filters ran the policies trained with the paper's QP target (checkpoints/paper-target),
#: whose cells are in docs/results/paper-target; the shipped policies' (weight averages) cells are in
#: docs/results/reproduction (shown where computed).
BESIDE = (
    ("EGCBF+ policy alone, paper's target (3 seeds)", PAPER_TARGET, ("egcbf+", "egcbf+-s1", "egcbf+-s2")),
    ("GCBF+ policy alone, paper's target (3 seeds)", PAPER_TARGET, ("gcbf+", "gcbf+-s1", "gcbf+-s2")),
    ("EGCBF+ policy alone, shipped (3 seeds)", REPRODUCTION, ("egcbf+", "egcbf+-s1", "egcbf+-s2")),
    ("GCBF+ policy alone, shipped (3 seeds)", REPRODUCTION, ("gcbf+", "gcbf+-s1", "gcbf+-s2")),
    ("dCBF-QP", REPRODUCTION, ("dcbf",)),
    ("cCBF-QP", REPRODUCTION, ("ccbf",)),
    ("nominal", REPRODUCTION, ("nominal",)),
)


def _rows(split: str) -> list[dict]:
    rows = []
    for run_file in sorted((RESULTS / split).glob("*/*/run.json")):
        run = json.loads(run_file.read_text())
        if not (run_file.parent / "metrics.json").exists():  # an evaluation still running: no finished size yet
            continue
        for r in json.loads((run_file.parent / "metrics.json").read_text()):
            rows.append({**r, "run": run, "row": run_file.parent.parent.name})
    return sorted(rows, key=lambda r: (r["run"]["obstacles"], r["num_agents"], r["row"]))


def _table(rows: list[dict]) -> str:
    lines = [
        "| controller | N | l (m) | obstacles | episodes | safe % | reach % | success % | reward | filtered % "
        "| slack / braked agent-steps | ms/step |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        run = r["run"]
        active = pct(r["filter_active"]) if "filter_active" in r else "-"
        slack = f"{r.get('qp_slack_steps', 0)} / {r.get('qp_failed', 0)}" if "qp_ms_median" in r else "-"
        lines.append(
            f"| {r['row']} | {r['num_agents']} | {run['area']:g} | {run['obstacles']} | {r['num_episodes']} | "
            f"{pct(r['safe_rate'])} | {pct(r['reach_rate'])} | {pct(r['success_rate'])} | {r['reward']:.2f} | "
            f"{active} | {slack} | {r['step_ms_median']:.0f} |"
        )
    lines += ["", "ms/step: the median wall time of one simulation step per episode, measured beside other jobs (not a "
              "benchmark; `benchmarks/filter_cost.py` is)."]  # fmt: skip
    seeds = sorted({r["run"]["seed"] for r in rows})
    commands = sorted({r["run"]["command"] for r in rows})
    lines += ["", f"Evaluation seed(s): {', '.join(map(str, seeds))}. Commands:", ""]
    lines += [f"    {c}" for c in commands]
    return "\n".join(lines)


def _reproduction_row(cells: Path, run: str, obstacles: int, n: int, area: float) -> dict | None:
    """The reproduction's cell of ``run`` in the folder ``cells`` (Table I at l = 4, else the scalability study), if
    computed."""
    base = cells if abs(area - 4.0) < 1e-9 else cells / "scale"
    path = base / f"{run}_obs{obstacles}" / f"N{n}.json"
    if not path.exists():
        return None
    cell = json.loads(path.read_text())
    return cell["row"] if abs(cell["meta"]["area"] - area) < 1e-3 else None


def _spread(values: list[float]) -> str:
    mean = sum(values) / len(values)
    return pct(mean) if len(values) == 1 else f"{pct(mean)} ({pct(min(values))}-{pct(max(values))})"


def _beside(rows: list[dict]) -> str:
    """Per case (N, arena, obstacles): the filtered controllers, then the reproduction's cells of the same case and
    seed (safe / success)."""
    lines = [
        "| N, l (m), obstacles, evaluation seed | controller | episodes | safe % | success % |",
        "|---|---|---|---|---|",
    ]
    cases: dict[tuple, list[dict]] = {}
    for r in rows:
        key = (int(r["run"]["obstacles"]), r["num_agents"], float(r["run"]["area"]), int(r["run"]["seed"]))
        cases.setdefault(key, []).append(r)
    for (obstacles, n, area, seed), group in sorted(cases.items()):
        case = f"{n}, {area:g}, {obstacles}, {seed}"
        learned = sorted((r for r in group if not r["row"].startswith("nominal")), key=lambda r: r["row"])
        for r in learned:
            lines.append(
                f"| {case} | **{r['row']}** | {r['num_episodes']} | {pct(r['safe_rate'])} | {pct(r['success_rate'])} |"
            )
        by_method: dict[str, list[dict]] = {}
        for r in learned:
            m = re.fullmatch(r"(?P<method>.+)-s\d+-(?P<filter>[a-z]+)", r["row"])
            if m is not None:
                by_method.setdefault(f"{m['method']} behind {m['filter']}", []).append(r)
        for name, rs in by_method.items():
            if len(rs) > 1:
                lines.append(
                    f"| {case} | **{name}, mean (min-max) over {len(rs)} training seeds** | {rs[0]['num_episodes']} | "
                    f"{_spread([r['safe_rate'] for r in rs])} | {_spread([r['success_rate'] for r in rs])} |"
                )
        for r in sorted((r for r in group if r["row"].startswith("nominal")), key=lambda r: r["row"]):
            lines.append(
                f"| {case} | {r['row']} (no policy) | {r['num_episodes']} | {pct(r['safe_rate'])} | "
                f"{pct(r['success_rate'])} |"
            )
        if seed != 0:
            continue
        for label, folder, runs in BESIDE:
            cells = [c for c in (_reproduction_row(folder, x, obstacles, n, area) for x in runs) if c is not None]
            if not cells:
                continue
            name = label if len(cells) == len(runs) else f"{label} ({len(cells)} of {len(runs)} seeds)"
            lines.append(
                f"| {case} | {name} | {cells[0]['num_episodes']} | {_spread([c['safe_rate'] for c in cells])} | "
                f"{_spread([c['success_rate'] for c in cells])} |"
            )
    lines += [
        "",
        "Bold: a learned policy behind the filter (`<method>-s<training seed>-<filter>`): the policies trained with "
        "the paper's QP target, now `checkpoints/paper-target/` (see the commands); `nominal-dcbf`: the nominal "
        "command behind the same filter. The other rows are the reproduction's cells (docs/results/paper-target for "
        "the paper's target, docs/results/reproduction for the shipped policies and the baselines; the same "
        "evaluation seed, episodes and arenas; mean (min-max) over training seeds).",
    ]
    return "\n".join(lines)


#: the reproduction's cells beside the LiDAR-only rows: (label, cell run name), shipped policies, obstacle map
LIDAR_BESIDE = (
    ("EGCBF+ behind its learned-CBF filter (`cbf`: LiDAR, as always)", "egcbf+_cbf"),
    ("EGCBF+ behind the dcbf filter reading the obstacle map", "egcbf+_dcbf"),
    ("nominal behind the dcbf filter reading the obstacle map", "nominal_dcbf"),
)


def _ci(row: dict, key: str) -> str:
    if "per_episode" not in row:  # a cell written before rows kept their episodes: no interval
        return f"{pct(row[key])} (no interval: per-episode values not kept)"
    iv = mean_ci([row["per_episode"][key]])
    return f"{pct(iv.estimate)} [{pct(iv.low)}, {pct(iv.high)}]"


def _hits(run: dict) -> str:
    """What the dcbf rows of a LiDAR-only run made of each hit: ``run.json``'s ``lidar_hits`` (runs written before
    the option existed read every hit as a point obstacle)."""
    return f"LiDAR hits as {run.get('lidar_hits', 'point')}s"


def _lidar(rows: list[dict]) -> str:
    """The LiDAR-only rows (``docs/results/filters/lidar``) beside the reproduction's cells of the same case, safe and
    success with 95 % intervals over episodes."""
    lines = ["| N, l (m), obstacles, evaluation seed | controller | obstacles perceived | episodes | safe % | "
             "success % |", "|---|---|---|---|---|---|"]  # fmt: skip
    cases = sorted({(int(r["run"]["obstacles"]), r["num_agents"], float(r["run"]["area"]), int(r["run"]["seed"]))
                    for r in rows})  # fmt: skip
    for obstacles, n, area, seed in cases:
        case = f"{n}, {area:g}, {obstacles}, {seed}"
        for r in (
            r for r in rows if (r["run"]["obstacles"], r["num_agents"], r["run"]["seed"]) == (obstacles, n, seed)
        ):
            lines.append(f"| {case} | **{r['row']}** | {_hits(r['run'])} | {r['num_episodes']} | "
                         f"{_ci(r, 'safe_rate')} | {_ci(r, 'success_rate')} |")  # fmt: skip
        if seed != 0:
            continue
        for label, run in LIDAR_BESIDE:
            cell = _reproduction_row(REPRODUCTION, run, obstacles, n, area)
            if cell is not None:
                seen = "LiDAR hits" if run.endswith("_cbf") else "obstacle map"
                lines.append(f"| {case} | {label} | {seen} | {cell['num_episodes']} | {_ci(cell, 'safe_rate')} | "
                             f"{_ci(cell, 'success_rate')} |")  # fmt: skip
    lines += ["", "Bold: `egcbf eval --obstacle-sensing lidar --lidar-hits plane|point` on the shipped checkpoint "
              "(`<method>-s<training seed>-dcbf-lidar[-plane]`; the rows without a suffix read hits as points) or "
              "the nominal controller; the other rows are the reproduction's cells "
              "(docs/results/reproduction, the same seed, episodes and arena). Intervals: 95 % bootstrap over "
              "episodes (`egcbf.evaluate.bootstrap.mean_ci`, one training seed)."]  # fmt: skip
    return "\n".join(lines)


def _faults_text(run: dict) -> str:
    """The fault levels a run applied (its ``run.json``'s non-zero ``faults``), ``none`` for the perfect world."""
    faults = run.get("faults") or {}
    on = [f"{k}={v:g}" for k, v in faults.items() if isinstance(v, (int, float)) and v and k != "gust_tau"]
    return ", ".join(on) if on else "none"


def _faults(rows: list[dict]) -> str:
    """The default-field rows (``docs/results/filters/faults``): each controller under the same faults, safe and
    success with 95 % intervals over episodes."""
    lines = ["| N, l (m), obstacles, evaluation seed | controller | faults | episodes | safe % | success % |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for r in rows:
        run = r["run"]
        case = f"{r['num_agents']}, {float(run['area']):g}, {run['obstacles']}, {run['seed']}"
        lines.append(f"| {case} | **{r['row']}** | {_faults_text(run)} | {r['num_episodes']} | "
                     f"{_ci(r, 'safe_rate')} | {_ci(r, 'success_rate')} |")  # fmt: skip
    lines += ["", "`egcbf eval --faults default` (the default field conditions of docs/robustness.md; commands "
              "below) on the shipped checkpoint behind the named filter (`<method>-s<training seed>-<filter>-default`)"
              " or the nominal controller behind it. Intervals: 95 % bootstrap over episodes "
              "(`egcbf.evaluate.bootstrap.mean_ci`, one training seed)."]  # fmt: skip
    return "\n".join(lines)


def main() -> None:
    rows = _rows("evaluation")
    body = _table(rows) if rows else "(no results yet)"
    if rows:
        body = _beside(rows) + "\n\nAll columns:\n\n" + body
    replace_section(DOC, "filters-evaluation", f"Generated by `.venv/bin/python docs/gen_filters.py`.\n\n{body}")
    lidar = _rows("lidar")
    if lidar:
        body = _lidar(lidar) + "\n\nAll columns:\n\n" + _table(lidar)
        replace_section(DOC, "filters-lidar", f"Generated by `.venv/bin/python docs/gen_filters.py`.\n\n{body}")
    faults = _rows("faults")
    if faults:
        body = _faults(faults) + "\n\nAll columns:\n\n" + _table(faults)
        replace_section(DOC, "filters-faults", f"Generated by `.venv/bin/python docs/gen_filters.py`.\n\n{body}")
    print(f"wrote {DOC}")


if __name__ == "__main__":
    main()
