"""Atomic file and directory replacement: a kill (even ``kill -9``) at any moment leaves either the complete old
content or the complete new one, never a half-written file or a missing directory.

Files: the new content is written to a hidden temporary file ``.NAME.PID.tmp`` in the same directory, then renamed
over the target with ``os.replace`` (atomic on POSIX within one file system). A temporary file left by a writer that
was killed (its PID is no longer alive) is removed at the next write of the same target; a live writer's is left alone.

Directories (``OUT/best``, checkpoints): ``os.replace`` cannot rename a directory over a non-empty one, so a
directory is replaced in three steps, a *swap*:

1. the new content is written completely into ``NAME.tmp`` (a kill here leaves ``NAME`` untouched);
2. ``NAME`` is renamed to ``NAME.old``;
3. ``NAME.tmp`` is renamed to ``NAME``; then ``NAME.old`` is deleted.

A kill between steps 2 and 3 leaves no ``NAME`` but a complete ``NAME.old`` (the previous content) and a complete
``NAME.tmp`` (the new one); :func:`recover_dir` (called by every reader) renames ``NAME.old`` back. A kill while
``NAME.old`` is being deleted leaves a complete ``NAME`` and a partial ``NAME.old`` that the next swap removes.

A write that fails for lack of room, a full disk (``ENOSPC``, ``EDQUOT``) or the file-size limit (``ulimit -f``,
``RLIMIT_FSIZE``: ``EFBIG``, with ``SIGXFSZ`` ignored as Python ignores it), raises :class:`WriteError`: one message
naming the file and the cause instead of the writer's own error (torch's "unexpected pos", an iostream error, a
safetensors ``SafetensorError``); the previous content is unchanged (:func:`writing` wraps any writer this way).
"""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

try:
    import resource
except ImportError:  # not POSIX (Windows): no file-size limit to read
    resource = None

__all__ = [
    "WriteError",
    "recover_dir",
    "remove_stale_temporaries",
    "replace_dir",
    "write_cause",
    "write_json_atomic",
    "write_text_atomic",
    "writing",
]

#: errno values that mean "no room for the write": the ones :func:`writing` turns into a :class:`WriteError`
_NO_ROOM = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
#: what a failed write keeps, by default (:func:`writing`)
_KEPT = "its previous content, if any, is unchanged"
#: below this many free bytes a file system counts as full when a writer's error does not say why it failed
_FULL_BYTES = 1 << 20


class WriteError(OSError):
    """A file could not be written for lack of room; the message names the file, the cause and what was kept.

    ``errno`` is the underlying ``ENOSPC``, ``EDQUOT`` or ``EFBIG``. ``exit_code`` (1) and :meth:`format_message`
    let the ``egcbf`` command print it as one ``Error:`` line without a traceback (``EGCBF_DEBUG=1`` shows it)."""

    exit_code = 1

    def __init__(self, message: str, code: int | None = None, path: Path | None = None):
        super().__init__(message)
        self.errno = code
        self.path = path

    def format_message(self) -> str:
        """The message (the ``egcbf`` command prints it as its ``Error:`` line)."""
        return str(self)


def _size(num_bytes: float) -> str:
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if num_bytes >= scale:
            return f"{num_bytes / scale:.1f} {unit}"
    return f"{int(num_bytes)} B"


def _errno_in(err: BaseException) -> int | None:
    """The errno behind ``err``: an ``OSError`` in its chain (torch's writer raises a ``RuntimeError`` whose context
    is the file object's ``OSError``), or ``os error N`` / ``[Errno N]`` in a message (safetensors)."""
    seen = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        if isinstance(err, OSError) and err.errno is not None:
            return err.errno
        found = re.search(r"os error (\d+)|\[Errno (\d+)\]", str(err))
        if found:
            return int(found.group(1) or found.group(2))
        err = err.__cause__ or err.__context__
    return None


def _fsize_limit() -> int | None:
    """The soft file-size limit (``ulimit -f``, ``RLIMIT_FSIZE``) in bytes; ``None`` if unlimited."""
    if resource is None:
        return None
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return None if soft == resource.RLIM_INFINITY else soft


def _free_bytes(path: Path) -> int | None:
    """Bytes this process may still write on the file system holding ``path`` (root may use the reserved blocks)."""
    folder = path
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        st = os.statvfs(folder)
        root = os.geteuid() == 0
    except (OSError, AttributeError):  # AttributeError: not POSIX (no statvfs)
        return None
    return (st.f_bfree if root else st.f_bavail) * st.f_frsize


def _guess_errno(path: Path) -> int | None:
    """Why a write of ``path`` failed when the writer's error does not say (torch's "unexpected pos" or iostream
    error): ``EFBIG`` if the file reached the file-size limit, ``ENOSPC`` if its file system is (nearly) full."""
    limit = _fsize_limit()
    if limit is not None and path.is_file() and path.stat().st_size >= limit:
        return errno.EFBIG
    free = _free_bytes(path)
    if free is not None and free < _FULL_BYTES:
        return errno.ENOSPC
    return None


def write_cause(code: int | None) -> tuple[str, str] | None:
    """``(cause, what to do)`` in words for a write that failed with errno ``code``; ``None`` unless it means no room
    (``ENOSPC``, ``EDQUOT``, ``EFBIG``)."""
    if code == errno.EFBIG:
        limit = _fsize_limit()
        if limit is None:
            return "the file is larger than its file system allows (File too large)", "write it to another file system"
        return (
            f"the file-size limit of this process (ulimit -f, RLIMIT_FSIZE: {_size(limit)}) was reached",
            "raise the limit (ulimit -f unlimited) and run again",
        )
    if code == errno.ENOSPC:
        return "no space left on device", "free some space on that disk (or write elsewhere) and run again"
    if code == errno.EDQUOT:
        return "disk quota exceeded", "free some of your files there (or write elsewhere) and run again"
    return None


@contextmanager
def writing(path: str | Path, kept: str = _KEPT) -> Iterator[Callable[[Path], Path]]:
    """Turn a failed write for lack of room inside the block into a :class:`WriteError` naming the file and the cause.

    ``kept`` says what the user still has (e.g. ``"the checkpoints already saved are unchanged"``). The block may
    write several files: it gets a function ``at(file) -> file`` that marks ``file`` as the one being written (named
    in the error; ``path`` until then). Other errors pass unchanged.
    """
    current = [Path(path)]

    def at(file: str | Path) -> Path:
        current[0] = Path(file)
        return current[0]

    try:
        yield at
    except WriteError:
        raise
    except Exception as err:
        code = _errno_in(err)
        if code is None and not isinstance(err, OSError):
            code = _guess_errno(current[0])
        words = write_cause(code)
        if words is None:
            raise
        cause, fix = words
        raise WriteError(f"could not write {current[0]}: {cause} ({kept}); {fix}", code, current[0]) from err


def _tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def _pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists on this machine (one of another user counts as alive)."""
    if pid <= 0:
        return True  # not a PID this module writes: never remove it
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Delete the temporary files ``.NAME.PID.tmp`` of ``path`` left by writers that died (their PID is not alive);
    a live process's (it may be writing right now) and this process's are kept. Returns the files removed."""
    path = Path(path)
    prefix, removed = f".{path.name}.", []
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return removed
    for entry in entries:
        name = entry.name
        pid = name[len(prefix) : -len(".tmp")]
        if not (name.startswith(prefix) and name.endswith(".tmp") and pid.isdigit()):
            continue
        if int(pid) == os.getpid() or _pid_alive(int(pid)):
            continue
        try:
            os.unlink(entry.path)
            removed.append(Path(entry.path))
        except OSError:  # removed by another writer meanwhile, or a directory: not ours to remove
            pass
    return removed


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` through a temporary file and ``os.replace``; returns ``path``. Stale temporary files
    of ``path`` are removed first (:func:`remove_stale_temporaries`); a full disk or the file-size limit raises
    :class:`WriteError` with ``path`` unchanged."""
    path = Path(path)
    tmp = _tmp_name(path)
    remove_stale_temporaries(path)
    try:
        with writing(path):
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
