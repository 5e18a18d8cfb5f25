"""The ``egcbf`` command group: the typer app, its one-line usage errors, ``--version``, the torch-thread choice
shared by the commands, and :func:`main` (the console script). The commands live in their own modules of
:mod:`egcbf.cli` and register themselves on :data:`app`."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Annotated

import torch
import typer
from typer.core import TyperGroup

from ..io.allocator import keep_freed_memory
from ..io.threads import choose_threads
from .checks import (
    _debug,
    usage_error,
)
from .choices import (
    choice_error,
)

__all__ = ["allocator_setting", "app", "main"]


class _OneLineErrors(TyperGroup):
    """The ``egcbf`` command group: a usage error that typer or click finds (a bad flag value, a value outside an
    option's choices, a missing argument, an unknown command or flag) ends the command with one ``Error:`` line
    naming the flag (exit code 2) instead of typer's boxed panel, whether it runs from :func:`main` or as ``app``
    (``typer.testing.CliRunner``); ``EGCBF_DEBUG=1`` re-raises."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        try:
            code = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except typer.Abort:
            typer.echo("Aborted!", err=True)
            sys.exit(1)
        except (MemoryError, ImportError) as err:  # anywhere in any command: one line, not a deep traceback
            if _debug() or (isinstance(err, ImportError) and "failed to map segment" not in str(err)):
                raise  # an ImportError that is not the loader running out of address space
            why = type(err).__name__ if isinstance(err, MemoryError) else "a library could not be mapped into memory"
            typer.echo(f"Error: out of memory ({why}); "
                       "free memory, raise the limit (ulimit -v, the cgroup's), or ask for less (fewer agents, "
                       "episodes or --batch)", err=True)  # fmt: skip
            sys.exit(2)
        except Exception as err:  # click's ClickException and UsageError (typer vendors click: duck-typed)
            if _debug() or not (hasattr(err, "format_message") and isinstance(getattr(err, "exit_code", None), int)):
                raise
            if type(err).__name__ == "NoArgsIsHelpError":
                err.show()
                sys.exit(0)
            typer.echo(f"Error: {_error_line(err)}", err=True)
            sys.exit(err.exit_code)
        sys.exit(code if isinstance(code, int) else 0)


def _error_line(err) -> str:
    """One line for a click usage error: the choices of an enum option spelled out (:func:`choice_error`), and a
    pointer to the command's ``--help``."""
    message = " ".join(err.format_message().split())
    param = getattr(err, "param", None)
    if param is not None and getattr(param, "opts", None):
        better = choice_error(param.opts[0], param.name or param.opts[0].lstrip("-"), message)
        message = better or message.replace("Value error, ", "")
    ctx = getattr(err, "ctx", None)
    return message + (f" (see `{ctx.command_path} --help`)" if ctx is not None else "")


app = typer.Typer(
    cls=_OneLineErrors,
    add_completion=False,
    no_args_is_help=True,
    help="Equivariant graph CBFs for quadrotor swarms. (EGCBF_DEBUG=1 shows the traceback of a usage error.)",
)


def _print_version(value: bool) -> None:
    if value:
        from .. import __version__

        typer.echo(f"egcbf {__version__} (torch {torch.__version__})")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool, typer.Option("--version", callback=_print_version, is_eager=True, help="print the version and exit")
    ] = False,
) -> None:
    """Equivariant graph CBFs for quadrotor swarms. (EGCBF_DEBUG=1 shows the traceback of a usage error.)"""


#: the process's allocator setting (:mod:`egcbf.io.allocator`), set by :func:`main`; recorded in run.json
_ALLOCATOR = "default (the CLI's entry point did not run)"


def allocator_setting() -> str:
    """The allocator setting :func:`main` chose (read when a command runs, after :func:`main` set it)."""
    return _ALLOCATOR


_THREADS_HELP = (
    "torch CPU threads (default: automatic: OMP_NUM_THREADS if set, else the CPUs available minus the busy ones "
    "(sampled over 0.2 s), at least 1, so that another busy process does not oversubscribe the cores); "
    "printed on stderr and recorded in run.json"
)


def _threads(requested: int | None) -> tuple[int, str]:
    """``(threads, reason)`` from :func:`egcbf.io.threads.choose_threads`; a bad ``--threads`` is a usage error."""
    try:
        return choose_threads(requested)
    except ValueError as err:
        usage_error(str(err), err)


@contextmanager
def _torch_threads(threads: int, reason: str) -> Iterator[None]:
    """Run the body with ``threads`` torch threads, said on stderr; the previous count is restored afterwards."""
    typer.echo(f"threads: {threads} ({reason})", err=True)
    saved = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(saved)


def main(argv: list[str] | None = None) -> None:
    """The ``egcbf`` command: keeps freed memory for reuse (:mod:`egcbf.io.allocator`) and runs :data:`app`, which
    prints a bad flag value or a missing argument as one ``Error:`` line naming the flag (exit code 2) instead of
    typer's boxed panel; ``EGCBF_DEBUG=1`` re-raises. ``argv``: the arguments (default: ``sys.argv[1:]``)."""
    global _ALLOCATOR
    _ALLOCATOR = keep_freed_memory()[1]
    app(args=argv, prog_name="egcbf")


if __name__ == "__main__":  # pragma: no cover
    main()
