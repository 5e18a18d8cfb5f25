"""docs/gcbfplus.md: every cell of the GCBF+ reference's table (issue 26) with our controllers beside its numbers.

Reads ``docs/results/gcbfplus/reference.json`` (the reference's pretrained GCBF+ on this CPU), our cells
``docs/results/gcbfplus/cells/<method>/<env>_N<N>_l<l>_obs<K>_T<steps>.json`` and ``speed.json``
(``benchmarks/gcbfplus_speed.py``), and writes the report. ``--run METHODS`` first evaluates the missing cells of
those methods (``nominal`` and ``dcbf``, the hand-crafted dCBF-QP, now; ``gcbf+`` / ``egcbf+`` from
``checkpoints/<robot>/<method>`` once they are shipped),
with the reference's N, l, obstacles and steps, on evaluation seed 0 (the reference used its seed 1234 with its own
sampler: the episodes differ, the settings and the metric definitions do not), and at least the reference's episode
count: :func:`our_episodes` raises it to 2560 agent-episodes per cell, because a few episodes leave the rates to the
draw (at N = 256, l = 22.6 and 256 steps, where only the goals within about 5 m can be reached, three episodes'
reach rate varies by about one point between draws even for the nominal controller alone). A cell computed with
fewer episodes than that is recomputed, and so is a learned method's cell whose ``checkpoint_sha256`` is not the
shipped checkpoint's (``state.json``'s ``weights_sha256``): replacing a checkpoint makes its cells pending.

    .venv/bin/python docs/gen_gcbfplus.py --run nominal,dcbf # evaluates the missing cells, then the report
    .venv/bin/python docs/gen_gcbfplus.py                    # the report from the committed cells only

Our robots for the reference's environments: SingleIntegrator -> ``single_integrator``, DoubleIntegrator ->
``double_integrator``, DubinsCar -> ``dubins_car``, LinearDrone -> ``linear_drone`` (docs/robots.md), CrazyFlie -> our
quadrotor (a different plant and command: for scale only). Obstacles are the reference's kinds (rectangles in 2-D,
spheres for the drones).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

ROOT = Path(__file__).resolve().parent
RESULTS = ROOT / "results" / "gcbfplus"
#: the reference's environments -> our robots (CrazyFlie: our quadrotor, another plant)
ROBOTS = json.loads((RESULTS / "reference.json").read_text())["robots"]
METHODS = ("nominal", "brisk", "ccbf", "dcbf", "gcbf+", "egcbf+")
#: the learned methods: a cell of theirs is current only for the shipped checkpoint's weights (its SHA-256)
LEARNED = ("gcbf+", "egcbf+")
#: agent-episodes per cell at least (:func:`our_episodes`)
MIN_AGENT_EPISODES = 2560


def our_episodes(row: dict) -> int:
    """Our episode count of a cell: the reference's, or enough for ``MIN_AGENT_EPISODES`` agent-episodes."""
    return max(int(row["episodes"]), math.ceil(MIN_AGENT_EPISODES / int(row["N"])))


def spread(metrics: dict, key: str, episodes: int) -> float:
    """The standard error (percentage points) of a rate's mean over ``episodes`` episodes, from our per-episode
    spread (``per_episode[key]``); 0 when it was not stored."""
    values = metrics.get("per_episode", {}).get(key, [])
    if len(values) < 2:
        return 0.0
    mean = sum(values) / len(values)
    var = sum((v - mean) ** 2 for v in values) / (len(values) - 1)
    return 100 * math.sqrt(var / episodes)


def current(method: str, row: dict) -> dict | None:
    """The committed cell of ``method``, or ``None`` if missing or computed with fewer than :func:`our_episodes`."""
    path = cell_path(method, row)
    if not path.exists():
        return None
    cell = json.loads(path.read_text())
    if cell["metrics"]["num_episodes"] < our_episodes(row):
        return None
    if method in LEARNED and cell.get("checkpoint_sha256") != shipped_sha256(method, row):
        return None  # computed from other weights than the shipped checkpoint's
    return cell


def checkpoint_dir(method: str, row: dict) -> Path:
    """The shipped checkpoint of a learned ``method`` for ``row``'s robot (the quadrotor's own for CrazyFlie)."""
    robot = ROBOTS[row["env"]]
    if robot == "quadrotor":
        return ROOT.parent / "checkpoints" / method
    return ROOT.parent / "checkpoints" / robot / method


def shipped_sha256(method: str, row: dict) -> str | None:
    """The SHA-256 of the shipped checkpoint's weights (its ``state.json``), ``None`` if it is not shipped."""
    state = checkpoint_dir(method, row) / "state.json"
    return json.loads(state.read_text())["weights_sha256"] if state.exists() else None


def cell_path(method: str, row: dict) -> Path:
    name = f"{row['env']}_N{row['N']}_l{row['l']:g}_obs{row['obstacles']}_T{row['steps']}.json"
    return RESULTS / "cells" / method.replace("+", "p") / name


def run_cell(method: str, row: dict) -> dict | None:
    """Evaluate one cell (``None`` if the method has no checkpoint for this robot yet)."""
    import torch

    from egcbf.control.controllers import make_controller
    from egcbf.evaluate.episodes import evaluate
    from egcbf.train.checkpoint import load_controller

    robot = ROBOTS[row["env"]]
    if method in ("nominal", "brisk", "ccbf", "dcbf"):
        make = lambda _cfg: make_controller(method, robot=robot)  # noqa: E731
        overrides = {}
    else:
        ckpt = checkpoint_dir(method, row)
        if not (ckpt / "model.safetensors").exists():
            return None
        ctrl, cfg = load_controller(ckpt)
        make = lambda _cfg: ctrl  # noqa: E731
        overrides = dict(cfg.env_overrides)
    torch.set_num_threads(1)
    rows, _ = evaluate(make, [int(row["N"])], area_size=float(row["l"]), num_obstacles=int(row["obstacles"]),
                       episodes=our_episodes(row), seed=0, max_steps=int(row["steps"]), show_progress=False,
                       env_overrides=overrides, robot=robot)  # fmt: skip
    out = dict(rows[0])
    out["per_episode"] = {k: rows[0]["per_episode"][k] for k in ("safe_rate", "reach_rate", "success_rate")}
    cell = {"method": method, "robot": robot, "setting": row, "metrics": out}
    if method in LEARNED:
        cell["checkpoint_sha256"] = shipped_sha256(method, row)
    return cell


def table(reference: list[dict]) -> str:
    head = "| env (ours) | N | l | obstacles | steps | episodes (reference / ours) | reference safe / reach / success |"
    head += "".join(f" {m} safe / reach / success |" for m in METHODS)
    lines = [head, "|---" * (7 + len(METHODS)) + "|"]
    for row in reference:
        cells = []
        for m in METHODS:
            cell = current(m, row)
            if cell is not None:
                r = cell["metrics"]
                cells.append(
                    f"{100 * r['safe_rate']:.1f} / {100 * r['reach_rate']:.1f} / {100 * r['success_rate']:.1f}"
                )
            else:
                cells.append("pending")
        ref = f"{row['safe']:g} / {row['reach']:g} / {row['success']:g}"
        setting = f"{row['N']} | {row['l']:g} | {row['obstacles']} | {row['steps']}"
        episodes = f"{row['episodes']} / {our_episodes(row)}"
        lines.append(
            f"| {row['env']} (`{ROBOTS[row['env']]}`) | {setting} | {episodes} | {ref} | " + " | ".join(cells) + " |"
        )
    return "\n".join(lines)


def meets_reference(metrics: dict, row: dict) -> bool:
    """Issue 26's bar for a learned method in one cell: at least as safe as the reference's pretrained GCBF+ (at
    least 99.9 % where it is 100 % safe) and at least as many goals reached."""
    safe, reach = 100 * metrics["safe_rate"], 100 * metrics["reach_rate"]
    need = 99.9 if row["safe"] >= 100 else row["safe"]
    return safe >= need and reach >= row["reach"]


def binomial_error(rate_percent: float, trials: int) -> float:
    """The binomial standard error (percentage points) of a rate measured on ``trials`` independent agents: a lower
    bound for agents of shared episodes, whose outcomes are correlated."""
    p = rate_percent / 100
    return 100 * math.sqrt(p * (1 - p) / trials)


def shortfall(metrics: dict, row: dict) -> str:
    """One cell that misses the bar: its setting, our safe and reach (with the standard error of our mean over
    episodes) against the reference's (with its binomial standard error over its agent-episodes, a lower bound)."""
    e = our_episodes(row)
    safe, reach = 100 * metrics["safe_rate"], 100 * metrics["reach_rate"]
    trials = int(row["N"]) * int(row["episodes"])
    return (f"{row['env']} N={row['N']} l={row['l']:g} obs={row['obstacles']} T={row['steps']} (safe {safe:.1f} "
            f"± {spread(metrics, 'safe_rate', e):.1f} vs {row['safe']:g} ± {binomial_error(row['safe'], trials):.1f}, "
            f"reach {reach:.1f} ± {spread(metrics, 'reach_rate', e):.1f} vs {row['reach']:g} "
            f"± {binomial_error(row['reach'], trials):.1f})")  # fmt: skip


def learned_summary(reference: list[dict]) -> str:
    """Per learned method: how many non-CrazyFlie cells meet the reference (and which do not), and Experiment B."""
    lines = []
    rows = [r for r in reference if r["env"] != "CrazyFlie"]
    exp_b = [r for r in rows if (r["env"], r["N"], r["l"], r["steps"]) == ("DoubleIntegrator", 256, 16, 1024)]
    for m in ("gcbf+", "egcbf+"):
        done = [(r, cell["metrics"]) for r in rows if (cell := current(m, r)) is not None]
        if not done:
            lines.append(f"- {m}: no cells yet.")
            continue
        short = [shortfall(c, r) for r, c in done if not meets_reference(c, r)]
        line = f"- {m}: {len(done) - len(short)} of {len(rows)} cells meet the reference ({len(done)} computed)"
        line += f"; short of it: {'; '.join(short)}." if short else "."
        b = [f"{r['obstacles']} obstacles {100 * c['success_rate']:.1f} %" for r, c in done if r in exp_b]
        if b:
            line += f" Experiment B success (target >= 80 %): {', '.join(b)}."
        lines.append(line)
    return "\n".join(lines)


def report() -> str:
    ref = json.loads((RESULTS / "reference.json").read_text())
    speed = RESULTS / "speed.json"
    parts = [
        "# The GCBF+ benchmark robots beside the reference's pretrained GCBF+",
        "",
        "Generated by `.venv/bin/python docs/gen_gcbfplus.py` from `docs/results/gcbfplus/` (issue 26). The "
        "reference's columns: " + ref["source"],
        "",
        "Ours: evaluation seed 0, the reference's N, l, obstacles and steps, and at least its episode count: at least "
        f"{MIN_AGENT_EPISODES} agent-episodes per cell (the episodes column: the reference's / ours), because a few "
        "episodes leave the rates to the draw (at N = 256, l = 22.6 and 256 steps only goals within about 5 m can be "
        "reached, and three episodes' reach rate moves by about one point between draws, the nominal controller's "
        "too); safe = never in collision "
        "(within 2 r of another agent or r of an obstacle), reach = within 2 r of the goal at some step, success = "
        "both, the reference's definitions (docs/metrics.md). nominal: the reference's nominal law; brisk: the robot's "
        "brisk law (`Robot.brisk_control`, no safety; below); ccbf / dcbf: the hand-crafted centralized / "
        "decentralized CBF-QP (`egcbf.robots.point_mass_qp` for the point masses and the Dubins car; the "
        "quadrotor's own for the CrazyFlie row). gcbf+ / egcbf+: `checkpoints/<robot>/<method>`; for the CrazyFlie "
        "row the quadrotor's shipped `checkpoints/<method>` (the `cpu` recipe). `pending`: not computed yet (a "
        "robot whose checkpoints are not shipped yet). CrazyFlie's row is our quadrotor: another plant and command.",
        "",
        table(ref["rows"]),
        "",
        "## Our learned controllers against the reference's",
        "",
        "Issue 26's bar, per cell but CrazyFlie's: at least as safe as the reference's pretrained GCBF+ (at least "
        "99.9 % where it is 100 % safe) and at least as many goals reached; Experiment B (double integrator, N = 256, "
        "l = 16, 0 / 32 / 128 obstacles, 1024 steps): success >= 80 %. Checkpoints: `checkpoints/<robot>/<method>` "
        "(how they were trained and chosen: [robots.md](robots.md)). A shortfall lists our rate ± the standard error "
        "of our mean over episodes, and the reference's ± its binomial standard error over its N x episodes agents "
        "(a lower bound: agents of one episode are not independent).",
        "",
        learned_summary(ref["rows"]),
        "",
        "## Brisk base law",
        "",
        "Reach at 256 steps in a large arena measures speed: at N = 256, l = 22.6 a goal is reachable only if the "
        "robot covers the distance in 7.68 s. The reference's nominal laws are gentle: the double integrator's LQR "
        "starts braking about half a metre from its goal, the Dubins car's law cruises at 0.46 m/s of the 0.8 its "
        "speed clip allows. A GCBF+ policy is a residual on that law (`u = clip(u_ref + 2 pi)`) trained towards a "
        "QP around it, so it is as slow as the law. `ModelConfig.base_law = 'brisk'` puts the policy around the "
        "robot's brisk law instead, and the QP teacher aims at it: the double integrator's is a cascade whose "
        "velocity target points straight at the goal with its larger axis at the 0.5 m/s limit until 12.5 cm out "
        "(gain 4 /s), tracked with a 0.06 s time constant, the Dubins car's the reference's law with its speed gain "
        "raised to cruise at `DubinsParams.brisk_speed` = 0.6 m/s (`k_v = k_a v_b / R`; an EGCBF+ around a law at "
        "the 0.8 m/s clip was 96.9 % safe at N = 16, l = 4 on validation, docs/results/gcbfplus/selection/"
        "brisk08_dub_e.txt). Both are equivariant under the robot's group (tested), "
        "and robots without one use their nominal law (`brisk` column). The nominal column stays the reference's law;"
        " the logged reward still measures the distance to it. A first double-integrator law that saturated both axes"
        " (a velocity target at the box's corner) reached as far but left agents stuck behind rectangles (with the "
        "dCBF-QP around it, validation seed 777, N = 256, l = 16, 128 rectangles, 1024 steps: reach 63 % against the "
        "nominal's 88 %; the straight law 84 %); its policies reached 62-74 % there "
        "(docs/results/gcbfplus/selection/brisk_chebyshev_di.txt). The double integrator's GCBF+ and EGCBF+ and "
        "the Dubins car's EGCBF+ act around their brisk laws (the car's trained on whole 256-step episodes with "
        "parked cars, docs/robots.md); the car's GCBF+ around its nominal law.",
        "",
        "## Step time",
        "",
    ]
    if speed.exists():
        data = json.loads(speed.read_text())
        worst = min(min(r["speedup"].values()) for r in data["results"])
        parts.append(f"At N = 256 our closed-loop step is {worst:.0f}x or more faster than the reference's in every "
                     "N = 256 setting (`benchmarks/gcbfplus_speed.py`; the table in "
                     "[benchmarks.md](benchmarks.md#against-the-gcbf-reference-at-n--256-issue-26)).")  # fmt: skip
    else:
        parts.append("Not measured yet: `benchmarks/gcbfplus_speed.py`.")
    return "\n".join(parts) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", default="", help="comma list of methods whose missing cells to evaluate first")
    args = ap.parse_args(argv)
    methods = [m for m in args.run.split(",") if m]
    bad = [m for m in methods if m not in METHODS]
    if bad:
        ap.error(f"--run: unknown method(s) {bad}; choose from {list(METHODS)}")
    for m in methods:
        for row in json.loads((RESULTS / "reference.json").read_text())["rows"]:
            path = cell_path(m, row)
            if current(m, row) is not None:
                continue
            try:
                cell = run_cell(m, row)
            except ValueError as err:  # a controller this robot does not have (the Dubins car's dCBF-QP)
                print(f"{m} {row['env']}: {err}")
                continue
            if cell is None:
                print(f"{m} {row['env']}: no checkpoint yet")
                continue
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(cell, indent=2) + "\n")
            r = cell["metrics"]
            print(f"{m} {path.name}: safe {100 * r['safe_rate']:.1f} reach {100 * r['reach_rate']:.1f}")
    (ROOT / "gcbfplus.md").write_text(report())
    print(f"wrote {ROOT / 'gcbfplus.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
