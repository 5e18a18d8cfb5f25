"""Markdown reports from evaluation results (``metrics.json`` + ``run.json`` written by ``egcbf eval``).

Sections of a markdown file between ``<!-- NAME:begin -->`` and ``<!-- NAME:end -->`` are regenerated in place,
so hand-written text around them survives.
"""

from __future__ import annotations

import json
import os
import platform
import sys
from collections.abc import Sequence
from pathlib import Path

from .atomic import write_text_atomic

__all__ = [
    "code_version",
    "cpu_name",
    "load_run",
    "machine_info",
    "md_table",
    "metrics_markdown",
    "number",
    "pct",
    "quote_section",
    "relative_link",
    "replace_block",
    "replace_section",
    "section_block",
]


def cpu_name() -> str:
    """The CPU model from ``/proc/cpuinfo`` (Linux), else what ``platform`` knows, for provenance records."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def machine_info() -> dict:
    """Provenance of a run: CPU model, logical cores, torch threads, torch / python versions, host name."""
    import torch

    return {
        "cpu": cpu_name(),
        "cores": os.cpu_count(),
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "python": sys.version.split()[0],
        "host": platform.node(),
    }


def code_version() -> str:
    """The package version, plus ``git describe --always`` of the source tree when it is a git checkout, with
    ``-dirty`` when the package sources differ from that commit (``src/``; results and reports written meanwhile do
    not count), e.g. ``0.4.0+g1a2b3c4-dirty``, for provenance records; never raises."""
    import subprocess

    from .._version import __version__

    here = Path(__file__).resolve().parent

    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", *args], cwd=here, capture_output=True, text=True, timeout=10)

    try:
        desc = git("describe", "--always", "--exclude", "*").stdout.strip()
        if desc and git("status", "--porcelain", "--", str(here.parent)).stdout.strip():
            desc += "-dirty"
    except (OSError, subprocess.SubprocessError):
        return __version__
    return f"{__version__}+g{desc}" if desc else __version__


def load_run(directory: str | Path) -> tuple[list[dict], dict]:
    """``(rows, meta)`` of an ``egcbf eval`` output directory."""
    d = Path(directory)
    rows_path = d / "metrics.json"
    if not rows_path.exists():
        raise FileNotFoundError(f"{rows_path} does not exist: run `egcbf eval ... --out {d}` first")
    rows = json.loads(rows_path.read_text())
    meta = json.loads((d / "run.json").read_text()) if (d / "run.json").exists() else {}
    return rows, meta


# ---------------------------------------------------------------------------------------------------- formats
def pct(rate: float, digits: int = 1) -> str:
    """A rate in ``[0, 1]`` in % with ``digits`` decimals, or with as many more (up to six) as keep a rate below 1
    from reading 100 and a rate above 0 from reading 0: ``pct(0.999765625) == "99.98"``, ``pct(1.0) == "100.0"``.
    The one rate format of every report of the package."""
    d = digits

    def hidden(d: int) -> bool:
        shown = round(100 * rate, d)
        return (rate < 1 and shown >= 100) or (rate > 0 and shown <= 0)

    while d < 6 and hidden(d):
        d += 1
    return f"{100 * rate:.{d}f}"


def number(x: float, decimals: int = 3) -> str:
    """``x`` with ``decimals`` decimals, except that a value that is not 0 but would print as 0 shows two
    significant digits instead: ``number(0.000234375) == "0.00023"``, ``number(0.0) == "0.000"``."""
    if x != 0 and round(x, decimals) == 0:
        return f"{x:.2g}"
    return f"{x:.{decimals}f}"


def md_table(head: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A markdown table: a header row, then one line per row."""
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def metrics_markdown(rows: Sequence[dict], *, label: str | None = None, timing: bool = True) -> str:
    """One markdown table row per swarm size, in the paper's format plus timing columns."""
    head = ["N", "Safe %", "Reach %", "Succ %", "Cost (min/max)", "Rew"]
    if label is not None:
        head.insert(0, "method")
    has_qp = timing and any("qp_ms_median" in r for r in rows)
    if timing:
        head.append("step ms")
    if has_qp:
        head += ["QP ms", "QPs with slack"]
    table = []
    for r in rows:
        cells = [
            str(r["num_agents"]),
            pct(r["safe_rate"]),
            pct(r["reach_rate"]),
            pct(r["success_rate"]),
            f"{number(r['cost'])} ({number(r['cost_min'], 2)}/{number(r['cost_max'], 2)})",
            f"{r['reward']:.3f}",
        ]
        if label is not None:
            cells.insert(0, label)
        if timing:
            cells.append(f"{r['step_ms_median']:.1f}")
        if has_qp:
            cells += [f"{r.get('qp_ms_median', float('nan')):.1f}", str(r.get("qp_slack_steps", 0))]
        table.append(cells)
    return md_table(head, table)


# ---------------------------------------------------------------------------------------------------- sections
def section_block(name: str, body: str) -> str:
    """``body`` between the markers ``<!-- name:begin -->`` and ``<!-- name:end -->``."""
    return f"<!-- {name}:begin -->\n{body.rstrip()}\n<!-- {name}:end -->"


def replace_block(text: str, name: str, body: str, heading: str | None = None) -> str:
    """``text`` with the block ``name`` (:func:`section_block`) replaced by ``body``, or appended (below
    ``heading``, e.g. ``"## Environment scaling"``, if given) when ``text`` has no such block."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    block = section_block(name, body)
    if begin in text and end in text:
        pre, rest = text.split(begin, 1)
        _, post = rest.split(end, 1)
        return pre + block + post
    top = f"{heading}\n\n" if heading else ""
    return text.rstrip() + ("\n\n" if text else "") + top + block + "\n"


def replace_section(path: str | Path, name: str, body: str, heading: str | None = None) -> None:
    """Replace (or append) the block between ``<!-- name:begin -->`` and ``<!-- name:end -->`` in ``path``
    (:func:`replace_block`); the file is replaced atomically (:func:`egcbf.io.atomic.write_text_atomic`)."""
    path = Path(path)
    text = path.read_text() if path.exists() else ""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, replace_block(text, name, body, heading))


def quote_section(page: str | Path, name: str, body: str) -> bool:
    """Rewrite the block ``name`` of ``page`` with ``body`` only where the page exists and has the markers (a page
    quoting a report opts in with them; one without is left alone), atomically; whether it was rewritten."""
    page = Path(page)
    if not page.exists():
        return False
    text = page.read_text()
    if f"<!-- {name}:begin -->" not in text or f"<!-- {name}:end -->" not in text:
        return False
    write_text_atomic(page, replace_block(text, name, body))
    return True


def relative_link(path: str | Path, page: str | Path) -> str:
    """``path`` relative to the folder of the markdown ``page`` that links to it, with ``/`` separators."""
    return Path(os.path.relpath(path, Path(page).parent)).as_posix()
