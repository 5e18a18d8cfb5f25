"""The summary of one ``benchmarks/gpu_check.sh`` run, from its results folder, as Markdown on stdout.

    python benchmarks/gpu_check_summary.py RESULTS [--device cuda]
    python benchmarks/gpu_check_summary.py docs/results/gpu_check --write-docs   # docs/benchmarks.md's CUDA section

``RESULTS`` holds what the script wrote (``info.json``, ``jobs.tsv``, ``*.log``, ``train_metrics.csv``, one
``eval-<device>-n<N>-<filter>/metrics.json`` per evaluation). Reported: the machine and versions; every job's exit
status and seconds (``137``: killed at its limit); the device tests' pytest line; the training updates' wall time;
and per evaluation the safe, reach and success rates and the median step time on the device beside the CPU's from
the same seed (one episode, the first ``--max-steps`` steps: the two float paths part ways over an episode, so the
rates are compared, not the trajectories). Works on a partial folder (a run cut short): what is missing says so.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import sys
from pathlib import Path

BEGIN, END = "<!-- gpu-check:begin -->", "<!-- gpu-check:end -->"
DOCS = Path(__file__).resolve().parents[1] / "docs" / "benchmarks.md"


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _jobs(res: Path) -> list[dict]:
    try:
        with open(res / "jobs.tsv", newline="") as f:
            return list(csv.DictReader(f, delimiter="\t"))
    except OSError:
        return []


def _pytest_line(res: Path) -> str:
    try:
        lines = (res / "tests.log").read_text().splitlines()
    except OSError:
        return "not run"
    found = [ln.strip("= ") for ln in lines if re.search(r"\d+ (passed|failed|error)", ln)]
    return found[-1] if found else "no result line (see tests.log)"


def _evals(res: Path) -> dict[tuple[int, str], dict[str, dict]]:
    """``{(N, filter): {device: metrics row}}``."""
    out: dict[tuple[int, str], dict[str, dict]] = {}
    for d in sorted(res.glob("eval-*")):
        m = re.fullmatch(r"eval-(.+)-n(\d+)-(\w+)", d.name)
        rows = _read_json(d / "metrics.json")
        if m and isinstance(rows, list) and rows:
            out.setdefault((int(m.group(2)), m.group(3)), {})[m.group(1)] = rows[0]
    return out


def summary(res: Path, device: str | None = None) -> str:
    info = _read_json(res / "info.json") or {}
    dev = (device or info.get("device") or "cuda").replace(":", "")
    lines = ["# benchmarks/gpu_check.sh", ""]
    if info:
        lines.append(
            f"Device `{info.get('device')}`{' (smoke run)' if info.get('smoke') else ''}: "
            f"{info.get('gpu') or 'no GPU'}; CPU {info.get('cpu')}; Python {info.get('python')}, torch "
            f"{info.get('torch')} (CUDA {info.get('cuda')}), torch-geometric {info.get('torch_geometric')}, egcbf "
            f"{info.get('egcbf')}."
        )
    else:
        lines.append("No `info.json`: the run stopped before its first job finished.")
    lines += ["", "| job | exit status | seconds | limit (s) |", "|---|---|---|---|"]
    lines += [f"| {j['job']} | {j['rc']} | {j['seconds']} | {j['limit_s']} |" for j in _jobs(res)]
    lines += ["", f"Device tests (`pytest -m device --device {info.get('device', dev)}`): {_pytest_line(res)}."]
    train = next((j for j in _jobs(res) if j["job"] == "train"), None)
    if train is not None:
        try:
            with open(res / "train_metrics.csv", newline="") as f:
                last = list(csv.DictReader(f))[-1]
            lines.append(
                f"Training: {last.get('step')} updates of EGCBF+ in {train['seconds']} s (job wall time, "
                f"start-up included); last validation safe {float(last['safe_rate']):.3f}."
            )
        except (OSError, IndexError, KeyError, ValueError):
            lines.append(f"Training: exit status {train['rc']} after {train['seconds']} s, no metrics.")
    evals = _evals(res)
    lines += ["", f"| N | filter | safe % ({dev} / cpu) | reach % ({dev} / cpu) | success % ({dev} / cpu) | "
              f"step ms ({dev} / cpu) | speed-up |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for (n, filt), by_dev in sorted(evals.items()):
        a, b = by_dev.get(dev), by_dev.get("cpu")

        def pair(key, scale=100.0, fmt="{:.2f}", a=a, b=b):
            return " / ".join(fmt.format(r[key] * scale) if r and key in r else "-" for r in (a, b))

        speed = "-"
        if a and b and a.get("step_ms_median") and b.get("step_ms_median"):
            speed = f"{b['step_ms_median'] / a['step_ms_median']:.1f}x"
        lines.append(f"| {n} | {filt} | {pair('safe_rate')} | {pair('reach_rate')} | {pair('success_rate')} | "
                     f"{pair('step_ms_median', 1.0, '{:.1f}')} | {speed} |")  # fmt: skip
    if not evals:
        lines.append("| - | - | no evaluation finished | | | | |")
    lines += ["", "Each evaluation: `egcbf eval --checkpoint checkpoints/egcbf+ --episodes 1 --seed 0 --max-steps S` "
              "(S = 200 at N = 512, 100 at N = 4096), l = 4 m at N = 512 and 8 m at N = 4096, float32; the CPU "
              "lane ran beside the device's, 4 torch threads each."]  # fmt: skip
    return "\n".join(lines) + "\n"


def write_docs(res: Path, docs: Path = DOCS) -> None:
    text = docs.read_text()
    if BEGIN not in text or END not in text:
        raise SystemExit(f"{docs} has no {BEGIN} ... {END} section")
    body = summary(res).split("\n", 2)[2]  # without its title
    root = docs.resolve().parents[1]
    rel = res.resolve().relative_to(root) if res.resolve().is_relative_to(root) else res
    head = f"Generated by `python benchmarks/gpu_check_summary.py {rel} --write-docs` from the committed run.\n\n"
    pre, rest = text.split(BEGIN, 1)
    docs.write_text(pre + BEGIN + "\n" + head + body + END + rest.split(END, 1)[1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", type=Path)
    ap.add_argument("--device", default=None, help="the device the run checked (default: from info.json)")
    ap.add_argument("--write-docs", action="store_true", help="rewrite docs/benchmarks.md's CUDA section")
    args = ap.parse_args(argv)
    if not args.results.is_dir():
        print(f"Error: {args.results} is not a folder", file=sys.stderr)
        return 2
    if args.write_docs:
        write_docs(args.results)
    else:
        sys.stdout.write(summary(args.results, args.device))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
