"""Atomic file and directory replacement: a kill (even ``kill -9``) at any moment leaves either the complete old
content or the complete new one, never a half-written file or a missing directory.

Files: the new content is written to a hidden temporary file in the same directory, then renamed over the target
with ``os.replace`` (atomic on POSIX within one file system).

Directories (``OUT/best``, checkpoints): ``os.replace`` cannot rename a directory over a non-empty one, so a
directory is replaced in three steps, a *swap*:

1. the new content is written completely into ``NAME.tmp`` (a kill here leaves ``NAME`` untouched);
2. ``NAME`` is renamed to ``NAME.old``;
3. ``NAME.tmp`` is renamed to ``NAME``; then ``NAME.old`` is deleted.

A kill between steps 2 and 3 leaves no ``NAME`` but a complete ``NAME.old`` (the previous content) and a complete
``NAME.tmp`` (the new one); :func:`recover_dir` (called by every reader) renames ``NAME.old`` back. A kill while
``NAME.old`` is being deleted leaves a complete ``NAME`` and a partial ``NAME.old`` that the next swap removes.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

__all__ = ["recover_dir", "replace_dir", "write_json_atomic", "write_text_atomic"]


def _tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` through a temporary file and ``os.replace``; returns ``path``."""
    path = Path(path)
    tmp = _tmp_name(path)
    try:
        with open(tmp, "w", newline="") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_json_atomic(path: str | Path, obj) -> Path:
    """``obj`` as indented JSON (trailing newline), written atomically to ``path``."""
    return write_text_atomic(path, json.dumps(obj, indent=2) + "\n")


def _old(final: Path) -> Path:
    return final.with_name(final.name + ".old")


def replace_dir(tmp: str | Path, final: str | Path) -> Path:
    """Replace the directory ``final`` by the complete directory ``tmp`` with the swap of the module doc."""
    tmp, final = Path(tmp), Path(final)
    old = _old(final)
    if final.exists():
        shutil.rmtree(old, ignore_errors=True)  # a leftover of an earlier swap (``final`` is complete then)
        os.replace(final, old)
    os.replace(tmp, final)
    shutil.rmtree(old, ignore_errors=True)
    return final


def recover_dir(final: str | Path) -> Path:
    """Undo a swap killed between its two renames: if ``final`` is missing and ``final.old`` exists, rename it back
    (or, if that is not allowed, return ``final.old`` to read from). Returns the directory to read."""
    final = Path(final)
    old = _old(final)
    if final.exists() or not old.is_dir():
        return final
    try:
        os.replace(old, final)
    except OSError:  # a read-only run directory: read the previous content where it is
        return old
    return final
