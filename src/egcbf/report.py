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

__all__ = ["code_version", "cpu_name", "load_run", "machine_info", "metrics_markdown", "replace_section"]


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
    """The package version, plus ``git describe --always --dirty`` of the source tree when it is a git checkout
    (e.g. ``0.4.0+g1a2b3c4-dirty``), for provenance records; never raises."""
    import subprocess

    from ._version import __version__

    try:
        desc = subprocess.run(
            ["git", "describe", "--always", "--dirty", "--exclude", "*"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
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


def _pct(x: float) -> str:
    return f"{100 * x:.1f}"


def metrics_markdown(rows: Sequence[dict], *, label: str | None = None, timing: bool = True) -> str:
    """One markdown table row per swarm size, in the paper's format plus timing columns."""
    head = ["N", "Safe %", "Reach %", "Succ %", "Cost (min/max)", "Rew"]
    if label is not None:
        head.insert(0, "method")
    has_qp = timing and any("qp_ms_median" in r for r in rows)
    if timing:
        head.append("step ms")
    if has_qp:
        head += ["QP ms", "QP steps with slack"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [
            str(r["num_agents"]),
            _pct(r["safe_rate"]),
            _pct(r["reach_rate"]),
            _pct(r["success_rate"]),
            f"{r['cost']:.3f} ({r['cost_min']:.2f}/{r['cost_max']:.2f})",
            f"{r['reward']:.3f}",
        ]
        if label is not None:
            cells.insert(0, label)
        if timing:
            cells.append(f"{r['step_ms_median']:.1f}")
        if has_qp:
            cells += [f"{r.get('qp_ms_median', float('nan')):.1f}", str(r.get("qp_slack_steps", 0))]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def replace_section(path: str | Path, name: str, body: str, heading: str | None = None) -> None:
    """Replace (or append) the block between ``<!-- name:begin -->`` and ``<!-- name:end -->`` in ``path``.

    ``heading`` (e.g. ``"## Environment scaling"``) is written above the block only when it is appended.
    """
    path = Path(path)
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    text = path.read_text() if path.exists() else ""
    block = f"{begin}\n{body.rstrip()}\n{end}"
    if begin in text and end in text:
        pre, rest = text.split(begin, 1)
        _, post = rest.split(end, 1)
        text = pre + block + post
    else:
        top = f"{heading}\n\n" if heading else ""
        text = text.rstrip() + ("\n\n" if text else "") + top + block + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
