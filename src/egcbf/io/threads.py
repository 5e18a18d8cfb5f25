"""How many torch CPU threads an evaluation should use (``egcbf eval`` / ``egcbf demo``).

Policy of :func:`choose_threads`, first match wins:

1. ``requested`` (the ``--threads`` option): an int >= 1, used as given.
2. ``OMP_NUM_THREADS`` in the environment, if it is an int >= 1: the user already chose.
3. Automatic: the CPUs this process may run on (``os.sched_getaffinity(0)``, else ``os.cpu_count()``) minus the
   busy ones, at least 1. "Busy" is measured where the OS allows it: the time those CPUs spent working during a
   0.2 s window at start (``/proc/stat``, Linux), rounded; elsewhere the 1-minute load average, rounded.

Why not torch's default (one thread per core): torch's threads meet at the end of every parallel operation, so
when another CPU-bound process takes a core from one of them the others wait, and every step slows down far more
than by that process's share (oversubscription). On the project's 2-core machine one evaluation step at 512 agents
took 67 ms with 2 threads on a quiet machine and 102 ms with 1 thread, but 409 ms with 2 threads while one other
CPU-bound process ran. So: all CPUs when they are free, one fewer per busy CPU.

Why a short sample rather than the load average: the load average lags by about a minute, so a job started seconds
ago barely shows yet, and a job that just ended (the user's previous command) still does: a benchmark running its
cases one after another was given one thread on an idle machine. The sample sees what runs now, on this process's
own CPUs only (so other containers' CPUs on a shared host do not count). Its price is 0.2 s at start. A burst
shorter than the window can still mislead it: pass ``--threads`` for timings that must be comparable.
"""

from __future__ import annotations

import os
import time

__all__ = ["available_cpus", "busy_cpus", "choose_threads", "load_average"]

#: the sampling window of :func:`busy_cpus` (s)
BUSY_WINDOW_S = 0.2


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


def _cpu_times(cpus: set[int]) -> tuple[float, float] | None:
    """``(busy, total)`` jiffies summed over ``cpus`` from ``/proc/stat``, or ``None`` where it cannot be read."""
    try:
        with open("/proc/stat") as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    busy = total = 0.0
    seen = 0
    for line in lines:
        name, *fields = line.split()
        if not (name.startswith("cpu") and name[3:].isdigit() and int(name[3:]) in cpus):
            continue
        values = [float(v) for v in fields[:8]]  # user nice system idle iowait irq softirq steal
        idle = values[3] + (values[4] if len(values) > 4 else 0.0)
        busy += sum(values) - idle
        total += sum(values)
        seen += 1
    return (busy, total) if seen else None


def busy_cpus(window: float = BUSY_WINDOW_S) -> float | None:
    """How many of this process's CPUs other work keeps busy now: their busy fraction over ``window`` seconds times
    their number (Linux ``/proc/stat``); ``None`` where it cannot be measured. This process sleeps meanwhile."""
    if not hasattr(os, "sched_getaffinity"):
        return None
    try:
        cpus = set(os.sched_getaffinity(0))
    except OSError:
        return None
    first = _cpu_times(cpus)
    if first is None:
        return None
    time.sleep(window)
    second = _cpu_times(cpus)
    if second is None or second[1] <= first[1]:
        return None
    return len(cpus) * (second[0] - first[0]) / (second[1] - first[1])


def choose_threads(requested: int | None = None) -> tuple[int, str]:
    """``(threads, reason)``: the torch CPU threads to use and a one-line reason (see the module docstring).

    ``requested`` (``--threads``) wins; a value that is not an int >= 1 raises ``ValueError`` naming ``--threads``.
    Otherwise a valid ``OMP_NUM_THREADS``, otherwise all available CPUs minus the busy ones (rounded), >= 1.
    """
    if requested is not None:
        if isinstance(requested, bool) or not isinstance(requested, int) or requested < 1:
            raise ValueError(f"--threads must be an integer >= 1, got {requested!r}")
        return requested, f"--threads {requested}"
    env = os.environ.get("OMP_NUM_THREADS", "").strip()
    if env.isdigit() and int(env) >= 1:
        return int(env), f"OMP_NUM_THREADS={env}"
    cpus = available_cpus()
    busy = busy_cpus()
    if busy is not None:
        return max(1, cpus - round(busy)), f"{cpus} CPUs available, {busy:.1f} busy"
    load = load_average()
    if load is None:
        return cpus, f"{cpus} CPUs available, load unknown"
    threads = max(1, cpus - round(load))
    return threads, f"{cpus} CPUs available, load {load:.1f}"
