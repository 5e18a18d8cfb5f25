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
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

__all__ = ["keep_freed_memory"]

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
