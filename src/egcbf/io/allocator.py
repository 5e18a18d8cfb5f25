"""Keep freed memory in the process for reuse (glibc): the CLI's allocator setting for CPU rollouts.

A learned policy's step at 512 agents allocates tens of tensors of a few MB (one row per graph edge) and frees them
within the step. With glibc's defaults, blocks above its mmap threshold are mapped from the OS and returned on free,
and a heap top above the trim threshold is returned too, so every step the kernel zero-fills the same pages again:
on the project's 2-core machine that page-faulting was about a quarter of an EGCBF+ step at 512 agents and a third
at 4096 (``benchmarks/policy_scaling.py`` measures it: the "Allocator" line of docs/benchmarks.md).
:func:`keep_freed_memory` turns both off (``mallopt``: ``M_MMAP_MAX = 0``, ``M_TRIM_THRESHOLD`` = 2^30), so freed
blocks stay in the heap and are reused. The price: the process keeps its peak memory until it exits, which is what
a CLI run wants.

``egcbf eval``, ``demo``, ``train`` and ``reproduce`` call it at start (it is process-wide, so the library never does
it behind a user's back: call it yourself in a script if you want it). ``EGCBF_KEEP_FREED_MEMORY=0`` in the
environment turns it off. Off glibc (macOS, Windows, musl) it does nothing and says so.

How much memory the process may still allocate (:func:`memory_headroom`, read by the CLI's memory checks before a
run) is the least of what each limit leaves (:func:`memory_limits`):

* the machine's free memory, ``MemAvailable`` of ``/proc/meminfo``;
* the address-space limit (``ulimit -v``, ``RLIMIT_AS``) less the process's current virtual size (``VmSize`` of
  ``/proc/self/status``: for a torch process it is gigabytes more than its resident memory, so the limit is compared
  with what is left, not with the process's RSS);
* the data-segment limit (``ulimit -d``, ``RLIMIT_DATA``) less ``VmData``;
* the memory limit of the process's cgroup and of each cgroup above it (cgroup v2: ``memory.max`` less
  ``memory.current``; v1: ``memory/memory.limit_in_bytes`` less ``memory.usage_in_bytes``; ``max`` or v1's huge
  default means none), usage counted without the inactive page cache (``inactive_file`` of ``memory.stat``), which
  the kernel reclaims before the limit is hit.

Each is a :class:`MemoryLimit` that says itself what it is, with its numbers; the roots ``/proc`` and
``/sys/fs/cgroup`` and the rlimit reader are arguments, so that tests can hand in fake ones.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

try:
    import resource
except ImportError:  # not POSIX (Windows): no rlimits
    resource = None

__all__ = ["Headroom", "MemoryLimit", "keep_freed_memory", "memory_headroom", "memory_limits"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_TRIM_THRESHOLD = 1 << 30


def keep_freed_memory() -> tuple[bool, str]:
    """Configure glibc's malloc to keep freed memory for reuse (module doc). Returns ``(applied, reason)``."""
    if os.environ.get("EGCBF_KEEP_FREED_MEMORY", "1").strip() == "0":
        return False, "off (EGCBF_KEEP_FREED_MEMORY=0)"
    name = ctypes.util.find_library("c")
    if name is None:
        return False, "off (no C library found)"
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError):
        return False, "off (not glibc: no mallopt)"
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    if not (mallopt(_M_MMAP_MAX, 0) and mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD)):
        return False, "off (mallopt refused)"
    return True, "glibc malloc keeps freed memory (no mmap, no trim)"


# ------------------------------------------------------------------------------------------- memory a run may use
#: a cgroup v1 "no limit" is the largest page-aligned 63-bit value; anything above this counts as none
_NO_CGROUP_LIMIT = 1 << 60
#: cgroup files by version: (limit, usage, memory.stat key of the reclaimable inactive page cache)
_CGROUP_FILES = {2: ("memory.max", "memory.current", "inactive_file"),
                 1: ("memory.limit_in_bytes", "memory.usage_in_bytes", "total_inactive_file")}  # fmt: skip


def _size(num_bytes: float) -> str:
    return f"{num_bytes / 2**30:.1f} GiB" if num_bytes >= 2**30 else f"{num_bytes / 2**20:.1f} MiB"


@dataclass(frozen=True)
class MemoryLimit:
    """One bound on the memory this process may still allocate: ``kind`` (``"free memory"``, ``"RLIMIT_AS"``,
    ``"RLIMIT_DATA"``, ``"cgroup"``), the ``available`` bytes it leaves, and ``text``, the whole of it in words
    with its numbers (``str(limit)``)."""

    kind: str
    available: int
    text: str

    def __str__(self) -> str:
        return self.text


class Headroom(int):
    """Bytes the process may still allocate (an ``int``) that remember the :class:`MemoryLimit` that binds."""

    limit: MemoryLimit

    def __new__(cls, limit: MemoryLimit) -> Headroom:
        value = super().__new__(cls, limit.available)
        value.limit = limit
        return value


def _read(path: Path) -> str | None:
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError):
        return None


def _kib_field(path: Path, key: str) -> int | None:
    """Bytes of the ``key:  N kB`` line of a ``/proc`` file (``meminfo``, ``self/status``); ``None`` if absent."""
    for line in (_read(path) or "").splitlines():
        name, _, value = line.partition(":")
        if name == key and value.split():
            try:
                return int(value.split()[0]) * 1024
            except ValueError:
                return None
    return None


def _free_memory(proc: Path) -> MemoryLimit | None:
    free = _kib_field(proc / "meminfo", "MemAvailable")
    if free is None:
        return None
    return MemoryLimit("free memory", free, f"the {_size(free)} of free memory (MemAvailable of {proc / 'meminfo'})")


#: (rlimit name, ulimit flag, what it limits, the /proc/self/status field of what the process uses of it)
_RLIMITS = (("RLIMIT_AS", "-v", "address-space", "VmSize"), ("RLIMIT_DATA", "-d", "data-segment", "VmData"))


def _rlimit(name: str, proc: Path, getrlimit: Callable[[int], tuple[int, int]]) -> MemoryLimit | None:
    """What the soft rlimit ``name`` (``RLIMIT_AS`` or ``RLIMIT_DATA``) leaves of the process's current size."""
    if resource is None or not hasattr(resource, name):
        return None
    _, flag, what, field = next(r for r in _RLIMITS if r[0] == name)
    soft = getrlimit(getattr(resource, name))[0]
    if soft == resource.RLIM_INFINITY or soft < 0:
        return None
    used = _kib_field(proc / "self" / "status", field)
    left = max(0, soft - (used or 0))
    uses = f"this process already uses {_size(used)} ({field})" if used is not None else f"{field} unknown"
    return MemoryLimit(name, left, f"the {_size(left)} left under the {what} limit (ulimit {flag}, {name}) of "
                       f"{_size(soft)}, of which {uses}")  # fmt: skip


def _cgroup_dirs(proc: Path, cgroup: Path) -> list[tuple[int, Path]]:
    """``(version, directory)`` of the process's memory cgroup and every cgroup above it (from
    ``/proc/self/cgroup``; the root alone when that cannot be read), deepest first."""
    lines = (_read(proc / "self" / "cgroup") or "").splitlines()
    places = []
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        if parts[0] == "0" and parts[1] == "":
            places.append((2, cgroup, parts[2]))
        elif "memory" in parts[1].split(","):
            places.append((1, cgroup / "memory", parts[2]))
    if not lines:
        places = [(2, cgroup, "/"), (1, cgroup / "memory", "/")]
    dirs = []
    for version, base, rel in places:
        here = base.joinpath(*[p for p in rel.split("/") if p not in ("", ".", "..")])
        while True:
            dirs.append((version, here))
            if here == base:
                break
            here = here.parent
    return dirs


def _cgroup_level(version: int, folder: Path) -> MemoryLimit | None:
    """What the memory limit of the cgroup ``folder`` leaves; ``None`` without a limit (or files) there."""
    limit_file, usage_file, cache_key = _CGROUP_FILES[version]
    limit, usage = (_read(folder / limit_file) or "").strip(), (_read(folder / usage_file) or "").strip()
    if not (limit.isdigit() and usage.isdigit()) or int(limit) >= _NO_CGROUP_LIMIT:
        return None  # "max", no such files (not this version, or not a memory cgroup), or v1's "no limit"
    cache = 0
    for line in (_read(folder / "memory.stat") or "").splitlines():
        key, _, value = line.partition(" ")
        if key == cache_key and value.strip().isdigit():
            cache = int(value)
    used = max(0, int(usage) - cache)
    left = max(0, int(limit) - used)
    return MemoryLimit("cgroup", left, f"the {_size(left)} left under the cgroup memory limit of {_size(int(limit))} "
                       f"({folder / limit_file}), of which {_size(used)} is in use ({usage_file} less inactive page "
                       "cache)")  # fmt: skip


def memory_limits(proc: str | Path = "/proc", cgroup: str | Path = "/sys/fs/cgroup",
                  getrlimit: Callable[[int], tuple[int, int]] | None = None) -> list[MemoryLimit]:  # fmt: skip
    """Every limit on what this process may still allocate that applies here (module doc), read from the roots
    ``proc`` and ``cgroup`` and with ``getrlimit`` (default ``resource.getrlimit``); unreadable ones are left out."""
    proc, cgroup = Path(proc), Path(cgroup)
    getrlimit = getrlimit or (resource.getrlimit if resource is not None else None)
    found = [_free_memory(proc)]
    if getrlimit is not None:
        found += [_rlimit(name, proc, getrlimit) for name, *_ in _RLIMITS]
    found += [_cgroup_level(version, folder) for version, folder in _cgroup_dirs(proc, cgroup)]
    return [limit for limit in found if limit is not None]


def memory_headroom(proc: str | Path = "/proc", cgroup: str | Path = "/sys/fs/cgroup",
                    getrlimit: Callable[[int], tuple[int, int]] | None = None) -> Headroom | None:  # fmt: skip
    """The bytes this process may still allocate: the least of :func:`memory_limits` (its ``limit`` says which binds,
    with the numbers); ``None`` if none can be read (not Linux)."""
    limits = memory_limits(proc, cgroup, getrlimit)
    return Headroom(min(limits, key=lambda limit: limit.available)) if limits else None
