"""benchmarks/gpu_check.sh, the CUDA check for a GPU machine, smoke-tested on the CPU (``--device cpu --smoke``):
every job runs and succeeds, the results and the summary land in the output folder; and a run cut short by its
budget keeps what it did, its unfinished jobs marked (killed: 137, not started: skipped)."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "gpu_check.sh"

pytestmark = pytest.mark.slow


def _run(out: Path, budget: int | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHON": sys.executable, "WHEELS": str(out / "no-wheels")}
    if budget is not None:
        env["GPU_CHECK_BUDGET_S"] = str(budget)
    return subprocess.run([str(SCRIPT), str(out), "--device", "cpu", "--smoke"], env=env, capture_output=True,
                          text=True, timeout=600)  # fmt: skip


def _jobs(out: Path) -> dict[str, str]:
    with tarfile.open(out / "gpu_check.tgz") as tar:
        rows = tar.extractfile("gpu_check/jobs.tsv").read().decode().splitlines()
        names = tar.getnames()
    return {r["job"]: r["rc"] for r in csv.DictReader(rows, delimiter="\t")}, names


def test_the_smoke_run_passes_on_the_cpu(tmp_path):
    res = _run(tmp_path)
    assert res.returncode == 0, res.stderr
    jobs, names = _jobs(tmp_path)
    evals = [f"eval-cpu-n16-{f}" for f in ("none", "dcbf")]
    assert jobs == dict.fromkeys(["info", "tests", "train", *evals], "0"), jobs
    assert all(f"gpu_check/{e}/metrics.json" in names for e in evals)
    summary = (tmp_path / "summary.md").read_text()
    assert "passed" in summary and " failed" not in summary
    assert "| 16 | dcbf |" in summary and "| 16 | none |" in summary
    assert "Training: 2 updates of EGCBF+" in summary
    # the docs section is regenerated from an unpacked run, the rest of the page kept
    with tarfile.open(tmp_path / "gpu_check.tgz") as tar:
        tar.extractall(tmp_path / "unpacked", filter="data")
    page = tmp_path / "benchmarks.md"
    page.write_text((ROOT / "docs" / "benchmarks.md").read_text())
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from gpu_check_summary import write_docs
    finally:
        sys.path.pop(0)
    write_docs(tmp_path / "unpacked" / "gpu_check", page)
    text = page.read_text()
    assert "CUDA has not been checked" not in text.split("<!-- gpu-check:begin -->")[1].split("<!-- gpu-check:end")[0]
    assert "| 16 | dcbf |" in text and text.count("<!-- gpu-check:begin -->") == 1
    assert text.endswith((ROOT / "docs" / "benchmarks.md").read_text().split("<!-- gpu-check:end -->")[1])


def test_a_run_cut_short_keeps_what_it_did(tmp_path):
    res = _run(tmp_path, budget=15)
    assert res.returncode == 0, res.stderr
    jobs, names = _jobs(tmp_path)
    assert jobs["info"] == "0" and "gpu_check/info.json" in names
    assert "skipped" in jobs.values(), jobs
    assert "no evaluation finished" in (tmp_path / "summary.md").read_text()
