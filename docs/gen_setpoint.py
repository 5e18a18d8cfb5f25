"""Regenerate the setpoint-substitution block of docs/deploy.md: what flying the acceleration command through the
Crazyflie firmware's controller, instead of our attitude loop, does to safety and success.

From the committed runs ``docs/results/setpoint/<controller>-<low level>-N<N>/`` (``metrics.json``, ``run.json``),
made with (``--filter none`` or ``dcbf``, ``--low-level attitude`` or ``setpoint``, ``N`` 64 and 512)::

    egcbf eval --checkpoint checkpoints/egcbf+ --filter F --num-agents N --area 4 --obstacles 0 --episodes 20 \\
        --seed 0 --threads 1 --no-progress --low-level L --out docs/results/setpoint/NAME

it writes the block ``setpoint-substitution``: the safe and success rates with their 95 % intervals (bootstrap over
the episodes, :func:`egcbf.evaluate.bootstrap.mean_ci`), the setpoint tracker's difference to our attitude loop with
its 95 % interval (paired: both low levels fly the same 20 scenes, so the bootstrap resamples per-episode
differences), a verdict per row, and a step response of the two low levels for one isolated drone (a simulation,
milliseconds, no files). Rows whose runs are missing are listed as pending.

Run: .venv/bin/python docs/gen_setpoint.py
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from egcbf.evaluate.bootstrap import Interval, mean_ci
from egcbf.io.report import pct, replace_section

ROOT = Path(__file__).parent
RESULTS = ROOT / "results" / "setpoint"
PAGE = ROOT / "deploy.md"
BLOCK = "setpoint-substitution"
HEADING = "## Flying setpoints: the firmware's controller instead of our attitude loop"
#: (directory prefix, label) of the controllers compared
CONTROLLERS = (("egcbf+", "EGCBF+ alone"), ("egcbf+_dcbf", "EGCBF+ behind `dcbf`"))
SIZES = (64, 512)
LOW_LEVELS = ("attitude", "setpoint")
KEYS = ("safe_rate", "success_rate")


def run_dir(controller: str, low_level: str, n: int) -> Path:
    return RESULTS / f"{controller}-{low_level}-N{n}"


def load(controller: str, low_level: str, n: int) -> dict | None:
    """The run's row and metadata ``{"row", "run"}``, or ``None`` if it is missing or unfinished; a run whose
    ``run.json`` says another low level or swarm size than its name is an error."""
    d = run_dir(controller, low_level, n)
    if not (d / "metrics.json").exists() or not (d / "run.json").exists():
        return None
    run = json.loads((d / "run.json").read_text())
    if not run.get("complete"):
        return None
    recorded = run.get("low_level", "attitude")  # runs of our own loop do not record it (the default)
    if recorded != low_level or run["num_agents"] != [n]:
        raise ValueError(f"{d}: run.json says low level {recorded!r} and N = {run['num_agents']}, not its name's")
    (row,) = json.loads((d / "metrics.json").read_text())
    return {"row": row, "run": run}


def paired_difference(a: dict, b: dict, key: str) -> Interval:
    """``a - b`` of ``key`` over the same episodes (``per_episode`` in episode order), with its 95 % interval."""
    ea, eb = a["row"]["per_episode"][key], b["row"]["per_episode"][key]
    if len(ea) != len(eb) or a["run"]["seed"] != b["run"]["seed"]:
        raise ValueError("a paired difference needs the same episodes (seed and count)")
    return mean_ci([[x - y for x, y in zip(ea, eb)]])


def _rate(res: dict, key: str) -> str:
    iv = mean_ci([res["row"]["per_episode"][key]])
    return f"{pct(iv.estimate)} [{pct(iv.low)}, {pct(iv.high)}]"


def _verdict(diffs: dict[str, Interval]) -> str:
    words = []
    for key, label in (("safe_rate", "safety"), ("success_rate", "success")):
        iv = diffs[key]
        if iv.low == iv.high == 0:
            words.append(f"{label} identical")
        elif iv.excludes_zero():
            words.append(f"{label} {'lower' if iv.estimate < 0 else 'higher'}")
        else:
            words.append(f"{label}: no difference resolved")
    return "; ".join(words)


def reading(found: list) -> str:
    """What the rows say, one sentence per compared pair (``found``: ``(label, N, runs, differences)``), and what a
    bootstrap interval at 100 % cannot say."""
    out = ["Reading:"]
    for label, n, res, diffs in found:
        safe = diffs["safe_rate"]
        att, sp = (res[ll]["row"]["safe_rate"] for ll in LOW_LEVELS)
        agents = res["setpoint"]["row"]["num_episodes"] * n
        if safe.low == safe.high == 0 and att == sp == 1.0:
            out.append(f"{label} at N = {n}: every agent of both runs is safe ({agents} agent-episodes each).")
        elif safe.excludes_zero():
            side = "loses" if safe.estimate < 0 else "gains"
            out.append(f"{label} at N = {n}: the firmware tracker {side} {abs(100 * safe.estimate):.1f} points of "
                       f"safety ({pct(att)} % to {pct(sp)} %; 95 % interval of the difference "
                       f"[{100 * safe.low:+.1f}, {100 * safe.high:+.1f}]).")  # fmt: skip
        else:
            unsafe = round((1 - sp) * agents), round((1 - att) * agents)
            out.append(f"{label} at N = {n}: no difference resolved ({pct(att)} % and {pct(sp)} %, "
                       f"{unsafe[1]} and {unsafe[0]} unsafe of {agents} agent-episodes).")  # fmt: skip
    if all(r["row"]["reach_rate"] == 1.0 for _, _, res, _ in found for r in res.values()):
        out.append("Every agent of every run reached its goal: success differs from safety nowhere.")
    out.append("Where every episode is at 100 % the bootstrap interval collapses to a point: it cannot bound rare "
               "failures, and 20 episodes cannot either.")  # fmt: skip
    return " ".join(out)


def step_response(accel: float = 2.0, times=(0.05, 0.1, 0.25, 0.5), cruise: float = 1.0) -> tuple[list, list, float]:
    """One isolated drone from hover under a constant sideways command ``accel`` (m/s^2), flown by our attitude loop
    and by the tracker with the evaluation's setpoint (position and velocity refreshed to the state every 25 ms):
    the realized acceleration (fraction of the command, over the control period ending at each of ``times``), and
    the tracker's mean deceleration (m/s^2) over 1 s of a level drone cruising at ``cruise`` m/s under a zero
    command (our attitude loop holds its speed exactly)."""
    from egcbf.env import EnvConfig
    from egcbf.env.swarm import advance
    from egcbf.robots import make_robot
    from egcbf.robots.quadrotor.dynamics import hover_state
    from egcbf.robots.quadrotor.nominal import track_acceleration

    f64 = torch.float64
    robot, cfg = make_robot("quadrotor"), EnvConfig(num_agents=1)
    a = torch.tensor([[[accel, 0.0, 0.0]]], dtype=f64)
    goals = torch.zeros(1, 1, 3, dtype=f64)
    out = []
    for low_level in ("attitude", "setpoint"):
        x, fractions = hover_state(torch.full((1, 1, 3), 2.0, dtype=f64)), []
        for k in range(1, round(max(times) / cfg.dt) + 1):
            x_next, _ = advance(robot, cfg, x, track_acceleration(x, a), goals, a if low_level == "setpoint" else None)
            if any(abs(k * cfg.dt - t) < 1e-9 for t in times):
                fractions.append(float((x_next[0, 0, 12] - x[0, 0, 12]) / cfg.dt) / accel)
            x = x_next
        out.append(fractions)
    x = hover_state(torch.full((1, 1, 3), 2.0, dtype=f64))
    x[..., 12] = cruise
    steps = round(1.0 / cfg.dt)
    for _ in range(steps):
        x, _ = advance(robot, cfg, x, track_acceleration(x, 0 * a), goals, 0 * a)
    return out[0], out[1], (cruise - float(x[0, 0, 12])) / (steps * cfg.dt)


def block() -> str:
    lines = [
        "Generated by `.venv/bin/python docs/gen_setpoint.py` from `docs/results/setpoint/` (`egcbf eval "
        "--checkpoint checkpoints/egcbf+ [--filter dcbf] --low-level attitude|setpoint`, l = 4 m, no obstacles, "
        "20 episodes, evaluation seed 0). Rates in % with 95 % bootstrap intervals over the episodes; the "
        "difference (setpoint tracker minus our attitude loop, in points) is paired over the same 20 scenes.",
        "",
        "| controller | N | low level | safe % | success % | safe: setpoint - attitude | success: setpoint - attitude "
        "| reading |",
        "|---|---|---|---|---|---|---|---|",
    ]
    pending, found = [], []
    for controller, label in CONTROLLERS:
        for n in SIZES:
            res = {ll: load(controller, ll, n) for ll in LOW_LEVELS}
            for ll in LOW_LEVELS:
                if res[ll] is None:
                    pending.append(f"`{run_dir(controller, ll, n).relative_to(ROOT.parent)}`")
            if any(r is None for r in res.values()):
                continue
            diffs = {k: paired_difference(res["setpoint"], res["attitude"], k) for k in KEYS}
            for ll in LOW_LEVELS:
                r = res[ll]
                cells = [label, str(n), "our attitude loop" if ll == "attitude" else "firmware setpoint tracker",
                         _rate(r, "safe_rate"), _rate(r, "success_rate")]  # fmt: skip
                if ll == "setpoint":
                    cells += [diffs["safe_rate"].text(100, 2), diffs["success_rate"].text(100, 2), _verdict(diffs)]
                    found.append((label, n, res, diffs))
                else:
                    cells += ["", "", ""]
                lines.append("| " + " | ".join(cells) + " |")
    if pending:
        lines += ["", "Pending (not run yet): " + ", ".join(pending) + "."]
    if found:
        lines += ["", reading(found)]
    ours, tracker, drag = step_response()
    times = ", ".join(f"{1000 * t:.0f}" for t in (0.05, 0.1, 0.25, 0.5))
    lines += [
        "",
        f"Step response of one isolated drone from hover to a 2 m/s^2 sideways command (realized acceleration over "
        f"the control period ending at {times} ms, as a fraction of the command): our attitude loop "
        + ", ".join(f"{v:.2f}" for v in ours)
        + "; the firmware tracker "
        + ", ".join(f"{v:.2f}" for v in tracker)
        + f". Under the evaluation's setpoint (position and velocity refreshed to the drone's own every 25 ms) a "
        f"drone cruising level at 1 m/s with a zero command slows by {drag:.2f} m/s^2 on average over 1 s (the "
        "position and velocity terms pull it back toward where it was at the last setpoint); under our attitude "
        "loop it keeps its speed.",
    ]
    return "\n".join(lines)


def main() -> None:
    replace_section(PAGE, BLOCK, block(), heading=HEADING)
    print(f"wrote the {BLOCK} block of {PAGE}")


if __name__ == "__main__":
    main()
