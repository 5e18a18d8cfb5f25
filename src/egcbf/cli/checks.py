"""Up-front validation of the command line's inputs, and the one way a user error leaves the CLI.

Every user error (a bad flag value, an unusable file or directory) ends the command with one or two lines on stderr,
``Error: <what was wrong, naming the flag or file, and the fix>``, and exit code 2, without a traceback. With the
environment variable ``EGCBF_DEBUG=1`` the underlying exception is raised instead (its traceback shows).

The checks run before any work starts (all swarm sizes, the output directory, the device, the checkpoint), so that
a mistake in the last of several swarm sizes does not throw away the earlier ones.
"""

from __future__ import annotations

import math
import os
import shutil
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import NoReturn

import torch
import typer

__all__ = [
    "UsageError",
    "available_memory",
    "check_env_flags",
    "check_policy_memory",
    "parse_device",
    "parse_sizes",
    "prepare_out",
    "require",
    "usage_error",
]


class UsageError(ValueError):
    """A user error of the command line (raised only under ``EGCBF_DEBUG=1``; otherwise printed)."""


def _debug() -> bool:
    return os.environ.get("EGCBF_DEBUG", "") not in ("", "0")


def usage_error(message: str, cause: BaseException | None = None) -> NoReturn:
    """End the command: ``Error: message`` on stderr and exit code 2 (or raise, under ``EGCBF_DEBUG=1``)."""
    if _debug():
        raise UsageError(message) from cause
    typer.echo(f"Error: {message}", err=True)
    raise typer.Exit(2)


def warn_cells(paths, problem: str, consequence: str) -> None:
    """One ``Warning:`` line on stderr about result files a report leaves out: ``"Warning: <count> <problem>:
    <at most five paths>; <consequence>"``; nothing when ``paths`` is empty."""
    if not paths:
        return
    import typer

    names = ", ".join(str(p) for p in paths[:5]) + (" ..." if len(paths) > 5 else "")
    typer.echo(f"Warning: {len(paths)} {problem}: {names}; {consequence}", err=True)


def warn_unreadable(paths, command: str) -> None:
    """:func:`warn_cells` for result files that exist but cannot be read (truncated or corrupted): they show as
    pending, and ``command`` recomputes them."""
    warn_cells(paths, "cell file(s) cannot be read (truncated or corrupted)",
               f"they show as pending ({command} recomputes them)")  # fmt: skip


def require(ok: bool, message: str) -> None:
    """``usage_error(message)`` unless ``ok``."""
    if not ok:
        usage_error(message)


def parse_sizes(text: str, flag: str = "--num-agents") -> list[int]:
    """Comma-separated positive integers, e.g. ``"8,16,64"`` -> ``[8, 16, 64]``."""
    try:
        sizes = [int(s) for s in text.replace(" ", "").split(",") if s]
    except ValueError:
        usage_error(f"{flag} must be comma-separated integers, got {text!r} (e.g. {flag} 8,16,64)")
    if not sizes or any(n < 1 for n in sizes):
        usage_error(f"{flag} needs positive integers, got {text!r}")
    return sizes


def parse_device(name: str, flag: str = "--device") -> torch.device:
    """A torch device that exists here: ``cpu``, or ``cuda[:k]`` when CUDA is available."""
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError, TypeError) as err:
        usage_error(f"{flag} {name!r} is not a device; use cpu or cuda", err)
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            usage_error(f"{flag} {name} was given but CUDA is not available here (torch.cuda.is_available() is False)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            usage_error(f"{flag} {name}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type != "cpu":
        usage_error(f"{flag} {name!r} is not supported; use cpu or cuda")
    return dev


def max_agents(area: float, separation: float, dim: int = 3) -> int:
    """The densest-packing bound on how many agents ``separation`` apart fit in ``[0, area]^dim`` (dim 2 or 3)."""
    if dim == 2:
        disc = math.pi * (separation / 2) ** 2
        return int(math.pi / (2 * math.sqrt(3)) * (area + separation) ** 2 / disc) if disc > 0 else 2**62
    ball = (4 / 3) * math.pi * (separation / 2) ** 3
    return int(math.pi / (3 * math.sqrt(2)) * (area + separation) ** 3 / ball) if ball > 0 else 2**62


def check_env_flags(
    sizes: Sequence[int],
    area: float,
    obstacles: int,
    max_steps: int | None,
    overrides: dict | None = None,
    robot: str | None = None,
) -> list:
    """The :class:`~egcbf.env.EnvConfig` of every swarm size, or a usage error naming the flag (``--area``,
    ``--obstacles``, ``--max-steps``, ``--num-agents``) if any of them is invalid or cannot be sampled; ``robot``:
    the swarm's robot (``None``: the default robot)."""
    from ..env import EnvConfig
    from ..env.sampling import packing_feasible
    from ..env.scenes import scene_boxes
    from ..robots import DEFAULT_ROBOT

    require(math.isfinite(area) and area > 0, f"--area must be a finite number > 0 (metres), got {area:g}")
    require(obstacles >= 0, f"--obstacles must be >= 0, got {obstacles}")
    require(max_steps is None or max_steps >= 1, f"--max-steps must be >= 1, got {max_steps}")
    kw = dict(overrides or {})
    if max_steps is not None:
        kw["max_steps"] = max_steps
    configs = []
    for n in sizes:
        try:
            cfg = EnvConfig.for_robot(
                robot or DEFAULT_ROBOT, num_agents=n, area_size=area, num_obstacles=obstacles, **kw
            )
        except (TypeError, ValueError) as err:
            usage_error(f"--num-agents {n}, --area {area:g}, --obstacles {obstacles}: {err}", err)
        sep = cfg.start_separation * cfg.agent_radius
        boxes = scene_boxes(cfg.scene, area, cfg.dim)
        if boxes is not None:  # starts (and goals) in part of the arena
            extents = tuple(hi - lo for lo, hi in boxes[0])
            require(
                packing_feasible(n, area, sep, dim=cfg.dim, extents=extents),
                f"--num-agents {n} cannot be placed in the {cfg.scene} scene's start region of --area {area:g} "
                f"({' x '.join(f'{e:g}' for e in extents)} m, agents {sep:g} m apart); use a larger --area or fewer "
                "agents",
            )
        elif not packing_feasible(n, area, sep, dim=cfg.dim):
            usage_error(
                f"--num-agents {n} cannot be placed in --area {area:g} (agents {sep:g} m apart: at most "
                f"{max_agents(area, sep, cfg.dim)} fit); use a larger --area or fewer agents"
            )
        # one trial placement (milliseconds; 0.2 s at N = 4096): the packing bound is necessary, not sufficient
        # (rejection sampling stalls well below it), and obstacles can crowd out the agents' starts and goals
        from ..env import SwarmEnv

        try:
            SwarmEnv(replace(cfg, num_envs=1)).reset(0)
        except ValueError as err:
            where = f"the {cfg.scene} scene's start region of " if boxes is not None else ""
            cause = f"--obstacles {obstacles} leave no room for" if obstacles else "there is no room for"
            usage_error(
                f"{cause} --num-agents {n} in {where}--area {area:g} ({err}); use "
                + ("fewer obstacles, " if obstacles else "")
                + "fewer agents or a larger --area",
                err,
            )
        configs.append(cfg)
    return configs


#: Peak memory per graph edge of a learned policy's step with hidden width 64 (measured on CPU for the shipped
#: EGCBF+ policy: 1.8 KB per edge, graph building included), rounded up; scaled linearly with the hidden width.
_BYTES_PER_EDGE_64 = 2048


def available_memory(device: torch.device) -> int | None:
    """Bytes the run may still allocate: free GPU memory for CUDA; on the CPU the least of free memory, what the
    address-space and data limits (``ulimit -v``, ``ulimit -d``) leave of the process's current size, and the
    cgroup's headroom (:func:`egcbf.io.allocator.memory_headroom`, whose ``limit`` names the one that binds);
    ``None`` where it cannot be told (then nothing is refused)."""
    if device.type == "cuda":
        try:
            return int(torch.cuda.mem_get_info(device)[0])
        except (RuntimeError, AssertionError):
            return None
    from ..io.allocator import memory_headroom

    return memory_headroom()


def policy_memory(num_agents: int, area: float, comm_radius: float, num_envs: int, hidden: int) -> tuple[int, int]:
    """``(bytes, edges)``: an estimate of a learned policy's peak memory for one step of ``num_envs`` environments.

    Edges: each agent's neighbours within ``comm_radius`` at the mean density ``N / l^3`` (an overestimate near the
    walls), at most ``N - 1``; bytes: :data:`_BYTES_PER_EDGE_64` per edge, scaled by ``hidden / 64``."""
    ball = (4 / 3) * math.pi * comm_radius**3
    neighbours = min(num_agents - 1, num_agents / area**3 * ball)
    edges = int(num_envs * num_agents * neighbours)
    return int(edges * _BYTES_PER_EDGE_64 * max(1.0, hidden / 64)), edges


def _size(num_bytes: float) -> str:
    return f"{num_bytes / 2**30:.1f} GiB" if num_bytes >= 2**30 else f"{num_bytes / 2**20:.1f} MiB"


def _available(free: int) -> str:
    """``free`` bytes in words: the limit that binds, with its numbers, when :func:`available_memory` knows it
    (e.g. "the 120.0 MiB left under the address-space limit (ulimit -v, RLIMIT_AS) of ..."), else "the X available"."""
    limit = getattr(free, "limit", None)
    return str(limit) if limit is not None else f"the {_size(free)} available"


def check_policy_memory(configs: Sequence, episodes: int, batch: int | None, hidden: int, device: torch.device) -> None:
    """Refuse (usage error, with the numbers) a learned-policy evaluation whose estimated step memory
    (:func:`policy_memory`) exceeds :func:`available_memory`, before anything is allocated."""
    from ..evaluate.episodes import episode_batch

    free = available_memory(device)
    if free is None:
        return
    for cfg in configs:
        n = cfg.num_agents
        envs = batch or episode_batch(n, episodes)
        need, edges = policy_memory(n, cfg.area_size, cfg.comm_radius, envs, hidden)
        if need > free:
            usage_error(
                f"--num-agents {n} at --area {cfg.area_size:g}: the learned policy needs about {_size(need)} "
                f"(~{edges:,} graph edges, {envs} episode(s) at once), more than {_available(free)}; "
                "use fewer agents, a larger --area or a smaller --batch"
            )


#: autograd keeps about this many times a forward pass's activations for the backward pass (training)
_BACKWARD_FACTOR = 4


def check_sweep_memory(cells: Sequence[tuple[int, float, int]], workers: int, hidden: int, comm_radius: float,
                       device: torch.device) -> None:  # fmt: skip
    """Refuse (usage error, with the numbers) a sweep whose largest learned cells, ``workers`` of them at once,
    would not fit: ``cells`` are ``(num_agents, area, episodes)`` of the learned cells (:func:`policy_memory` of
    each, episodes batched as :func:`egcbf.evaluate.episodes.evaluate` batches them)."""
    from ..evaluate.episodes import episode_batch

    free = available_memory(device)
    if free is None or not cells:
        return
    needs = sorted(
        ((policy_memory(n, area, comm_radius, episode_batch(n, eps), hidden)[0], n, area) for n, area, eps in cells),
        reverse=True,
    )
    parallel = needs[: max(1, min(workers, len(needs)))]
    total = sum(need for need, _, _ in parallel)
    if total > free:
        need, n, area = parallel[0]
        usage_error(
            f"the sweep's largest learned cell (N = {n}, l = {area:g}) needs about {_size(need)}, and {len(parallel)} "
            f"cell(s) at once about {_size(total)}, more than {_available(free)}; use fewer --workers or "
            "smaller --num-agents / --scale-sizes"
        )


def check_training_memory(cfg, device: torch.device) -> None:
    """Refuse (usage error, with the numbers) a training run whose estimated peak memory does not fit: a minibatch
    of ``batch_size`` graphs of ``num_agents`` agents at the densest training area, with gradients
    (:data:`_BACKWARD_FACTOR` times a forward pass), or the rollout of ``rollout_envs`` environments."""
    from ..env import EnvConfig

    free = available_memory(device)
    if free is None:
        return
    area = min(cfg.area_sizes or [cfg.area_size])
    comm = EnvConfig(num_agents=cfg.num_agents, area_size=area, **dict(cfg.env_overrides)).comm_radius
    fit, edges = policy_memory(cfg.num_agents, area, comm, cfg.batch_size, cfg.model.hidden)
    fit *= _BACKWARD_FACTOR
    rollout, _ = policy_memory(cfg.num_agents, area, comm, cfg.rollout_envs, cfg.model.hidden)
    need = max(fit, rollout)
    if need > free:
        usage_error(
            f"training needs about {_size(need)} (a minibatch of {cfg.batch_size} graphs of {cfg.num_agents} agents at "
            f"l = {area:g}: ~{edges:,} edges, with gradients), more than {_available(free)}; lower "
            "batch_size or num_agents in the --config, or use --device cuda"
        )


def holding_checkpoint(path: Path) -> Path | None:
    """The checkpoint or training-run directory that ``path`` (a file to write) would land in, or ``None``: the
    nearest ancestor holding ``model.safetensors`` or ``state.json`` (a checkpoint), or ``checkpoints/`` beside a
    ``config.json`` (a training run). Commands write there only when that is their job (``train``, ``average``)."""
    for parent in Path(os.path.abspath(path)).parents:
        if (parent / "model.safetensors").exists() or (parent / "state.json").exists():
            return parent
        if (parent / "checkpoints").is_dir() and (parent / "config.json").exists():
            return parent
    return None


def check_output_file(out: Path, overwrite: bool, companions: Sequence[str] = (), flag: str = "--out") -> None:
    """Refuse (usage error) to write the file ``out`` and its ``companions`` (suffixes appended to its name, e.g.
    ``".json"``) when one is a directory, lands inside a checkpoint or training run (:func:`holding_checkpoint`;
    even with ``overwrite``), or exists without ``overwrite``. Checked before any work starts."""
    targets = [out, *(out.with_name(out.name + c) for c in companions)]
    for path in targets:
        require(not path.is_dir(), f"{flag} {out}: {path} is a directory; name the file to write")
    home = holding_checkpoint(out)
    require(home is None, f"{flag} {out} is inside the checkpoint or training run {home}; write it elsewhere (it "
            "would sit beside, or replace, the files that checkpoint loads from)")  # fmt: skip
    for path in targets:
        require(overwrite or not path.exists(), f"{flag} {out}: {path} exists; pass --overwrite to replace it")


def prepare_out(
    out: Path,
    overwrite: bool,
    results: Sequence[str],
    flag: str = "--out",
    run_dir_ok: bool = False,
    lock: bool = True,
) -> Path:
    """Make ``out`` an empty-of-results, writable directory that this process alone writes into, before any work
    starts.

    ``out`` is locked for the rest of the command (:func:`egcbf.io.locks.hold_dir`): a second command writing there at
    the same time is refused, naming the first. ``results`` are glob patterns of the files a run writes there (e.g.
    ``metrics.json``, ``*_N*.gif``). If any exists, the run is refused unless ``overwrite``, in which case they are
    deleted first (so that a new run never mixes with an old one's renders). The current directory (``--out ''``
    from an empty shell variable, or ``.``), a dangling symbolic link and, unless ``run_dir_ok``, a training run's
    directory are refused. ``lock=False`` (a directory that only receives a report file, e.g. ``--report``'s)
    checks that it is a writable directory, nothing else.
    """
    from ..io.locks import DirLockedError, hold_dir

    if lock and str(out) in ("", "."):
        usage_error(f"{flag} is empty or '.' (the current directory); name a directory for the results, e.g. "
                    f"{flag} out/results")  # fmt: skip
    if out.is_symlink() and not out.exists():
        usage_error(f"{flag} {out} is a symbolic link to {os.readlink(out)}, which does not exist; choose another "
                    f"{flag} or create its target")  # fmt: skip
    if out.exists() and not out.is_dir():
        usage_error(f"{flag} {out} is a file, not a directory; choose another {flag}")
    if (
        lock
        and not run_dir_ok
        and out.is_dir()
        and ((out / "checkpoints").is_dir() or (out / "model.safetensors").exists())
    ):
        usage_error(f"{flag} {out} is a training run or checkpoint directory; write results elsewhere (e.g. "
                    f"{flag} {out / 'eval'})")  # fmt: skip
    try:
        if lock:
            hold_dir(out, " ".join(["egcbf", *sys.argv[1:2]]))
    except DirLockedError as err:
        usage_error(str(err), err)
    except OSError as err:
        usage_error(f"{flag} {out} is not writable ({err.strerror or err}); choose another {flag}", err)
    found = sorted({p for pattern in results for p in out.glob(pattern)}) if out.is_dir() else []
    if found and not overwrite:
        usage_error(
            f"{flag} {out} already holds results ({found[0].name}); pass --overwrite to replace them "
            f"or choose another {flag}"
        )
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write_test.{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as err:
        usage_error(f"{flag} {out} is not writable ({err.strerror or err}); choose another {flag}", err)
    for p in found:
        if p.is_dir():
            shutil.rmtree(p)
        else:
            p.unlink()
    return out
