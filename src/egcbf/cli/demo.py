"""The body of ``egcbf demo``: several controllers on the same episodes, one table, one comparison GIF.

Every controller runs :func:`egcbf.cli.eval.run_eval` on the same swarm, area, obstacles, episodes and evaluation
seed, so the episodes (starts, goals, obstacles) are identical and the rows compare like with like. The first
episode of each is recorded and drawn side by side (:func:`egcbf.viz.render.render_comparison_gif`).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Annotated

import torch
import typer

from ..control.names import FILTER_LABELS, filter_label, path_name, split_method
from ..io.atomic import write_json_atomic, write_text_atomic
from ..io.report import machine_info, number, pct
from .checks import (
    check_env_flags,
    check_policy_memory,
    parse_device,
    prepare_out,
    require,
    usage_error,
)
from .choices import (
    DemoMethod,
)
from .eval import EVAL_RESULTS, build_controller, run_eval, say_run_checkpoint
from .root import _THREADS_HELP, _threads, _torch_threads, allocator_setting, app

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
#: a learned method behind a run-time filter, ``METHOD:FILTER`` (:mod:`egcbf.control.names`)
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
    record: bool = False,
) -> dict:
    """Run every controller of ``sources`` (``{name: checkpoint directory, or None for a hand-crafted
    controller}``, the first is the demo's method) into ``OUT/<name>/``; print and write the table
    (``OUT/summary.md``), the comparison GIF (``OUT/compare_N<n>.gif``) and a top-down still of the first
    controller, and ``OUT/demo.json``; with ``record`` also ``OUT/<name>/episode.mcap`` (the first episode as ROS 2
    messages, :mod:`egcbf.ros.record`, with a learned controller's CBF values). Inputs are checked by the caller.
    Returns the summary written to demo.json."""
    from ..viz.render import render_comparison_gif, render_topdown

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
            record_to=out_dir(out, name) / "episode.mcap" if record else None,
            record_cbf=record and ckpt is not None,
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
            out / f"compare_N{num_agents}.gif", panels, first.goals, first.centers, first.radii, boxes=first.boxes,
            area_size=area, title=title,
        )  # fmt: skip
        main, rec = next(iter(episodes_seen.items()))
        png = render_topdown(
            out_dir(out, f"{main}_N{num_agents}_topdown.png"), torch.stack(rec.positions), rec.goals, rec.centers,
            rec.radii, torch.stack(rec.collided), boxes=rec.boxes, area_size=area,
            title=f"{describe(main)}, N = {num_agents}",
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


def _demo_source(name: str, checkpoints: Path) -> Path | None:
    """The checkpoint directory of a learned method (``checkpoints/<name>``), or ``None`` for a hand-crafted
    controller name; a clear error naming the path and the training command if a learned method has none."""
    from ..algo.config import LEARNED_METHODS
    from ..control.controllers import CONTROLLERS
    from ..control.names import FILTERS, split_method
    from ..marl import MARL_METHODS

    if name in CONTROLLERS:
        return None
    try:
        method = split_method(name)[0]
    except ValueError:
        method = None
    if method in MARL_METHODS and name == method:  # a MARL baseline: its checkpoint folder, no filter
        from ..marl.checkpoint import is_marl_checkpoint

        path = checkpoints / name
        if not is_marl_checkpoint(path):
            usage_error(f"--checkpoints: no {name} checkpoint at {path} (marl.json + model.safetensors); train one "
                        f"with `python -m egcbf.marl.ppo_lagrangian --out runs/{name}` and copy it there")  # fmt: skip
        return path
    if method not in LEARNED_METHODS:
        usage_error(
            f"unknown method {name!r}: a learned method {sorted(LEARNED_METHODS)}, a MARL baseline "
            f"{list(MARL_METHODS)}, "
            f"one behind a run-time filter as METHOD:FILTER with FILTER in {list(FILTERS[1:])} (e.g. egcbf+:dcbf), "
            f"or a controller {sorted(CONTROLLERS)}"
        )
    name = method
    from ..train.checkpoint import find_checkpoint

    path = checkpoints / name
    try:
        found = find_checkpoint(path, prefer_best=True)
    except FileNotFoundError as err:
        usage_error(
            f"--checkpoints: no {name} checkpoint at {path} (config.json + model.safetensors); train one with "
            f"`egcbf train --algo {name} --out runs/{name}` and pass --checkpoints with a folder holding {name}/",
            err,
        )
    say_run_checkpoint(path, found, "--checkpoints")
    return found


#: what a learned --method is compared with by default ("{method}": the method itself behind a run-time filter)
_DEMO_COMPARE = ("{method}:dcbf", "gcbf+", "nominal", "dcbf")


@app.command()
def demo(
    checkpoints: Annotated[
        Path, typer.Option(help="directory holding one checkpoint directory per learned method (egcbf+/, gcbf+/, ...)")
    ] = Path("checkpoints"),
    method: Annotated[
        DemoMethod, typer.Option(help="a learned method (its checkpoint in CHECKPOINTS) or a hand-crafted controller")
    ] = DemoMethod.egcbf_plus,
    compare: Annotated[
        str | None,
        typer.Option(
            "--compare",
            "--baseline",
            help="controllers run on the same episodes, comma list; METHOD:FILTER is a learned method behind a "
            "run-time filter (--filter of eval); 'none' to skip (default: METHOD:dcbf,gcbf+,nominal,dcbf; nominal "
            "for a hand-crafted --method)",
        ),
    ] = None,
    num_agents: Annotated[int, typer.Option("--num-agents", help="agents per episode")] = 128,
    area: Annotated[float, typer.Option(help="side l of the arena [0, l]^3 (m)")] = 4.0,
    obstacles: Annotated[int, typer.Option(help="number of sphere obstacles")] = 8,
    episodes: Annotated[int, typer.Option(help="episodes per controller (the same ones for every controller)")] = 4,
    seed: Annotated[int, typer.Option(help="evaluation seed")] = 0,
    out: Annotated[Path, typer.Option(help="output directory")] = Path("out/demo"),
    max_steps: Annotated[int | None, typer.Option(help="episode length (default: the env's)")] = None,
    device: Annotated[str, typer.Option(help="cpu | cuda | cuda:K")] = "cpu",
    threads: Annotated[int | None, typer.Option(help=_THREADS_HELP.replace("run.json", "demo.json"))] = None,
    render: Annotated[bool, typer.Option("--render/--no-render", help="the comparison GIF and a still")] = True,
    progress: Annotated[bool, typer.Option("--progress/--no-progress")] = True,
    record: Annotated[
        bool,
        typer.Option("--record", help="also OUT/<controller>/episode.mcap: each first episode as ROS 2 messages"),
    ] = False,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="replace the results already in OUT (default: refuse to mix runs)")
    ] = False,
) -> None:
    """The main job: the learned EGCBF+ policy, alone and behind the dCBF run-time filter, beside GCBF+, the nominal
    controller and the hand-crafted dCBF-QP on the same episodes (128 agents, l = 4, 8 obstacles by default): one
    table, OUT/summary.md, a GIF of the first episode of every controller side by side (OUT/compare_N<n>.gif),
    OUT/<controller>/metrics.json and OUT/demo.json."""
    from ..control.names import split_method

    method = method.value
    if compare is None:  # a hand-crafted --method alone is compared with the nominal controller only
        learned = _demo_source(method, checkpoints) is not None
        default = [c.format(method=method) for c in _DEMO_COMPARE] if learned else ["nominal"]
        names = [method, *(c for c in default if c != method)]
    else:
        extra = [c for c in compare.replace(" ", "").split(",") if c and c.lower() != "none"]
        names = list(dict.fromkeys([method, *extra]))
    sources = {name: _demo_source(name, checkpoints) for name in names}  # fail before any work
    n_threads, reason = _threads(threads)
    require(episodes >= 1, f"--episodes must be >= 1, got {episodes}")
    require(num_agents >= 1, f"--num-agents must be >= 1, got {num_agents}")
    dev = parse_device(device)
    if record:
        from ..ros.messages import MissingExtraError, require_extra

        try:
            require_extra("--record")
        except MissingExtraError as err:
            usage_error(str(err), err)
    check_env_flags([num_agents], area, obstacles, max_steps)
    from ..control.resolve import POLICY
    from ..robots import DEFAULT_ROBOT

    for name, ckpt in sources.items():  # every checkpoint loads and fits in memory, before the first method runs
        if ckpt is not None:
            train_cfg = build_controller(POLICY, ckpt, "--checkpoints", device=dev).train_config
            base = split_method(name)[0]
            require(  # the label comes from what the weights are, not from the folder's name
                train_cfg.algo == base,
                f"--checkpoints: {ckpt} holds {train_cfg.algo} weights (its model.safetensors says so), not {base}; "
                f"the folders of --checkpoints are named after their method (put {base}'s checkpoint there)",
            )
            require(
                train_cfg.robot == DEFAULT_ROBOT,
                f"--checkpoints: {ckpt} drives a {train_cfg.robot}; the demo compares quadrotor controllers (for "
                f"another robot: `egcbf eval --checkpoint {ckpt}`, or docs/gen_planar.py --gif for the unicycle)",
            )
            configs = check_env_flags([num_agents], area, obstacles, max_steps, train_cfg.env_overrides)
            if hasattr(train_cfg, "model"):  # a graph policy (a MARL actor needs no graph memory)
                check_policy_memory(configs, episodes, None, train_cfg.model.hidden, dev)
    prepare_out(out, overwrite, ("demo.json", "summary.md", f"compare_N{num_agents}.gif"))
    for name in names:
        prepare_out(out_dir(out, name), overwrite, EVAL_RESULTS)
    with _torch_threads(n_threads, reason):
        run_demo(
            sources,
            num_agents=num_agents,
            area=area,
            obstacles=obstacles,
            episodes=episodes,
            seed=seed,
            out=out,
            max_steps=max_steps,
            device=device,
            progress=progress,
            threads_reason=reason,
            allocator=allocator_setting(),
            render=render,
            record=record,
        )
