"""How many torch CPU threads an evaluation should use (``egcbf eval`` / ``egcbf demo``).

Policy of :func:`choose_threads`, first match wins:

1. ``requested`` (the ``--threads`` option): an int >= 1, used as given.
2. ``OMP_NUM_THREADS`` in the environment, if it is an int >= 1: the user already chose.
3. Automatic: the CPUs this process may run on (``os.sched_getaffinity(0)``, else ``os.cpu_count()``) minus the
   other load on the machine (the 1-minute load average, rounded), at least 1.

Why not torch's default (one thread per core): torch's threads meet at the end of every parallel operation, so
when another CPU-bound process takes a core from one of them the others wait, and every step slows down far more
than by that process's share (oversubscription). On the project's 2-core machine one evaluation step at 512 agents
took 67 ms with 2 threads on a quiet machine and 102 ms with 1 thread, but 409 ms with 2 threads while one other
CPU-bound process ran. So: all CPUs when they are free, one fewer per busy CPU.

The load average is a lagging, machine-wide estimate: a job started seconds ago barely shows yet, and inside a
container it may count the host's load (then this errs towards fewer threads, the safe side). Pass ``--threads``
for timings that must be comparable.
"""

from __future__ import annotations

import os

__all__ = ["available_cpus", "choose_threads", "load_average"]


def available_cpus() -> int:
    """CPUs this process may run on: its affinity mask where the OS has one, else ``os.cpu_count()`` (>= 1)."""
    if hasattr(os, "sched_getaffinity"):
        try:
            return max(1, len(os.sched_getaffinity(0)))
        except OSError:
            pass
    return max(1, os.cpu_count() or 1)


def load_average() -> float | None:
    """The machine's 1-minute load average, or ``None`` where the OS does not report one (Windows)."""
    try:
        return float(os.getloadavg()[0])
    except (AttributeError, OSError):
        return None


def choose_threads(requested: int | None = None) -> tuple[int, str]:
    """``(threads, reason)``: the torch CPU threads to use and a one-line reason (see the module docstring).

    ``requested`` (``--threads``) wins; a value that is not an int >= 1 raises ``ValueError`` naming ``--threads``.
    Otherwise a valid ``OMP_NUM_THREADS``, otherwise all available CPUs minus the rounded 1-minute load, >= 1.
    """
    if requested is not None:
        if isinstance(requested, bool) or not isinstance(requested, int) or requested < 1:
            raise ValueError(f"--threads must be an integer >= 1, got {requested!r}")
        return requested, f"--threads {requested}"
    env = os.environ.get("OMP_NUM_THREADS", "").strip()
    if env.isdigit() and int(env) >= 1:
        return int(env), f"OMP_NUM_THREADS={env}"
    cpus = available_cpus()
    load = load_average()
    if load is None:
        return cpus, f"{cpus} CPUs available, load unknown"
    threads = max(1, cpus - round(load))
    return threads, f"{cpus} CPUs available, load {load:.1f}"
