"""One writer per results directory: an exclusive advisory lock held for the whole of a command that writes there.

Two ``egcbf eval`` (or ``demo``, ``train``, ``reproduce``) runs started at the same moment into one ``--out`` would
both pass the "already holds results" check and overwrite each other's files; the lock makes the second one stop
before it starts, naming the first::

    with DirLock(out, "egcbf eval"):
        ...  # check for old results, evaluate, write

or, for the rest of the process (what a command line does), ``hold_dir(out, "egcbf eval")``.

The lock is a POSIX ``flock`` on ``OUT/.egcbf.lock`` (the file holds the holder's command and PID for the message;
the kernel drops the lock when its process dies, even under ``kill -9``, so a stale file never blocks anyone). It
is re-entrant within a process (a command that locks a directory and then calls code that locks it again does not
block itself); between processes it is exclusive. On a platform without ``fcntl`` (Windows) nothing is locked.
A directory the lock created and nothing else wrote to (a command refused for bad settings) is removed with the
lock, so a refused command leaves nothing behind.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

__all__ = ["LOCK_NAME", "DirLock", "DirLockedError", "hold_dir"]

#: The lock file inside a locked directory.
LOCK_NAME = ".egcbf.lock"
#: directories this process holds: resolved path -> [open lock file, depth, the directories the lock created]
_HELD: dict[Path, list] = {}


class DirLockedError(RuntimeError):
    """Another process holds the directory's lock."""


class DirLock:
    """``with DirLock(directory, what):`` holds an exclusive lock on ``directory`` (created if missing), or raises
    :class:`DirLockedError` at once naming the holder. ``what`` (e.g. ``"egcbf eval"``) is recorded for the
    message the next process gets."""

    def __init__(self, directory: str | Path, what: str):
        self.directory = Path(directory)
        self.path = self.directory / LOCK_NAME
        self.what = what
        self.key: Path | None = None  # the held directory (a key of _HELD) while entered

    def __enter__(self) -> DirLock:
        try:
            import fcntl
        except ImportError:  # pragma: no cover - Windows
            return self
        created = [d for d in (self.directory, *self.directory.parents) if not d.exists()]
        self.directory.mkdir(parents=True, exist_ok=True)
        key = self.directory.resolve()
        if key in _HELD:  # this process holds it already
            _HELD[key][1] += 1
            self.key = key
            return self
        file = open(self.path, "a+")
        try:
            fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = ""
            for _ in range(20):  # the holder writes its name just after taking the lock: give it a moment
                file.seek(0)
                holder = file.read().strip()
                if holder:
                    break
                time.sleep(0.005)
            holder = holder or "another process"
            file.close()
            raise DirLockedError(
                f"{self.directory} is being written by {holder}; wait for it to finish, stop it, or choose another "
                "output directory"
            ) from None
        file.seek(0)
        file.truncate()
        file.write(f"{self.what} (pid {os.getpid()})")
        file.flush()
        _HELD[key] = [file, 1, created]
        self.key = key
        return self

    def __exit__(self, *exc) -> None:
        key, self.key = self.key, None
        entry = _HELD.get(key) if key is not None else None
        if entry is not None:
            entry[1] -= 1
            if entry[1] == 0:
                if entry[2]:
                    _remove_if_unused(entry[2])
                entry[0].close()  # closing releases the lock
                del _HELD[key]


def _remove_if_unused(created: list[Path]) -> None:
    """Remove the locked directory ``created[0]`` and the parents the lock made for it (``created[1:]``) if it
    holds nothing but the lock file (still held: no one else is writing there)."""
    try:
        if [p.name for p in created[0].iterdir()] != [LOCK_NAME]:
            return
        (created[0] / LOCK_NAME).unlink()
        for directory in created:
            directory.rmdir()  # raises, and stops, at a parent that something else now uses
    except OSError:  # something arrived meanwhile, or it went: leave it
        pass


def hold_dir(directory: str | Path, what: str) -> None:
    """Lock ``directory`` (:class:`DirLock`) for the rest of the process: the kernel releases it at exit."""
    DirLock(directory, what).__enter__()
