"""The body of ``egcbf demo``: several controllers on the same episodes, one table, one comparison GIF.

Every controller runs :func:`egcbf.cli_eval.run_eval` on the same swarm, area, obstacles, episodes and evaluation
seed, so the episodes (starts, goals, obstacles) are identical and the rows compare like with like. The first
episode of each is recorded and drawn side by side (:func:`egcbf.render.render_comparison_gif`).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch
import typer

from .atomic import write_json_atomic, write_text_atomic
from .cli_eval import run_eval
from .filter_names import FILTER_LABELS, filter_label, path_name, split_method
from .report import machine_info, number, pct

__all__ = ["DESCRIPTIONS", "FILTER_DESCRIPTIONS", "demo_table", "describe", "out_dir", "run_demo"]

#: what each controller is, for the demo's table
DESCRIPTIONS = {
    "egcbf+": "EGCBF+ (learned, equivariant)",
    "egcbf": "EGCBF (learned, equivariant)",
    "gcbf+": "GCBF+ (learned)",
    "gcbf": "GCBF (learned)",
    "nominal": "nominal (no safety filter)",
    "dcbf": "dCBF-QP (hand-crafted)",
    "ccbf": "cCBF-QP (hand-crafted)",
}
#: a learned method behind a run-time filter, ``METHOD:FILTER`` (:mod:`egcbf.filter_names`)
FILTER_DESCRIPTIONS = {k: f"+ {v}" for k, v in FILTER_LABELS.items()}


def describe(name: str) -> str:
    """The table's label of a controller name (``egcbf+``, ``dcbf``, ``egcbf+:dcbf``, ...)."""
    method, filt = split_method(name)
    if filt == "none":
        return DESCRIPTIONS.get(method, method)
    return filter_label(DESCRIPTIONS.get(method, method).split(" (")[0], filt)


def out_dir(out: Path, name: str) -> Path:
    """The folder of a controller's results (``METHOD:FILTER`` as ``METHOD_FILTER``: no colon in paths)."""
    return out / path_name(name)


def demo_table(rows: dict[str, dict], header: str) -> str:
    """One plain-text table of the controllers' metrics rows ``{name: row}`` (rates in %), with a legend."""
    head = f"{'controller':32s} {'safe %':>7s} {'reach %':>8s} {'success %':>10s} {'collisions':>11s} {'ms/step':>8s}"
    lines = [header, "", head, "-" * len(head)]
    for name, r in rows.items():
        lines.append(
            f"{describe(name):32s} {pct(r['safe_rate']):>7} {pct(r['reach_rate']):>8} "
            f"{pct(r['success_rate']):>10} {number(r['cost']):>11} {r['step_ms_median']:8.2f}"
        )
    lines += [
        "",
        "safe: the agent never collided in the episode; reach: it came within 2 agent radii of its goal; success: "
        "both.",
        "collisions: collision events per agent per episode; ms/step: median wall time of one simulation step.",
    ]
    return "\n".join(lines)


def run_demo(
    sources: dict[str, Path | None],
    *,
    num_agents: int,
    area: float,
    obstacles: int,
    episodes: int,
    seed: int,
    out: Path,
    max_steps: int | None,
    device: str,
    progress: bool,
    threads_reason: str,
    allocator: str,
    render: bool = True,
) -> dict:
    """Run every controller of ``sources`` (``{name: checkpoint directory, or None for a hand-crafted
    controller}``, the first is the demo's method) into ``OUT/<name>/``; print and write the table
    (``OUT/summary.md``), the comparison GIF (``OUT/compare_N<n>.gif``) and a top-down still of the first
    controller, and ``OUT/demo.json``. Inputs are checked by the caller. Returns the summary written to demo.json."""
    from .render import render_comparison_gif, render_topdown

    t0 = time.time()
    rows, episodes_seen = {}, {}
    for name, ckpt in sources.items():
        filt = split_method(name)[1]
        recorded = run_eval(
            controller=name if ckpt is None else None,
            num_agents=str(num_agents),
            area=area,
            obstacles=obstacles,
            episodes=episodes,
            seed=seed,
            out=out_dir(out, name),
            render=False,
            max_steps=max_steps,
            batch=None,
            device=device,
            dtype="float32",
            progress=progress,
            checkpoint=ckpt,
            threads_reason=threads_reason,
            overwrite=True,  # checked by the caller for every controller
            allocator=allocator,
            record=render,
            filter=filt,
        )
        rows[name] = _read_row(out_dir(out, name))
        if num_agents in recorded:
            episodes_seen[name] = recorded[num_agents]
    header = (
        f"The same {episodes} episode(s) for every controller: N = {num_agents} agents, l = {area:g} m, "
        f"{obstacles} obstacles, evaluation seed {seed}."
    )
    table = demo_table(rows, header)
    typer.echo("\n" + table + "\n")
    write_text_atomic(out / "summary.md", "```\n" + table + "\n```\n")
    written = [out / "summary.md"]
    if episodes_seen:
        first = next(iter(episodes_seen.values()))
        panels = {
            describe(n).split(" (")[0]: (torch.stack(e.positions), torch.stack(e.collided))
            for n, e in episodes_seen.items()
        }
        title = f"first episode, N = {num_agents}, l = {area:g} m, {obstacles} obstacles (red: colliding)"
        gif = render_comparison_gif(
            out / f"compare_N{num_agents}.gif", panels, first.goals, first.centers, first.radii, area_size=area,
            title=title,
        )  # fmt: skip
        main, rec = next(iter(episodes_seen.items()))
        png = render_topdown(
            out_dir(out, f"{main}_N{num_agents}_topdown.png"), torch.stack(rec.positions), rec.goals, rec.centers,
            rec.radii, torch.stack(rec.collided), area_size=area, title=f"{describe(main)}, N = {num_agents}",
        )  # fmt: skip
        written += [gif, png]
    names = list(sources)
    summary = {
        "command": " ".join(["egcbf", *sys.argv[1:]]),
        "method": names[0],
        "compared": names[1:],
        "checkpoints": {k: None if v is None else str(v) for k, v in sources.items()},
        "num_agents": num_agents,
        "area": area,
        "obstacles": obstacles,
        "episodes": episodes,
        "seed": seed,
        "max_steps": max_steps,
        "metrics": rows,
        "wall_s": round(time.time() - t0, 1),
        "threads": torch.get_num_threads(),
        "threads_reason": threads_reason,
        "allocator": allocator,
        "machine": machine_info(),
    }
    write_json_atomic(out / "demo.json", summary)
    for p in [*written, out / "demo.json"]:
        typer.echo(f"wrote {p}")
    return summary


def _read_row(directory: Path) -> dict:
    return json.loads((directory / "metrics.json").read_text())[0]
