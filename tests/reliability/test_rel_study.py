"""``egcbf study`` tells the truth about where its report comes from and what is left to do: ``--report-only --root
COPY`` names COPY as its source, and ``--plan`` counts the cells whose stored result is gone."""

import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2] / "docs" / "results" / "equivariance"


@pytest.fixture(scope="module")
def copy(tmp_path_factory):
    dst = tmp_path_factory.mktemp("study") / "copy"
    shutil.copytree(ROOT, dst)
    return dst


def test_the_report_names_the_root_it_was_generated_from(cli, copy, tmp_path):
    report = tmp_path / "equivariance.md"
    res = cli("study", "--report-only", "--root", copy, "--report", report)
    assert res.exit_code == 0, res.output
    text = report.read_text()
    assert f"from the result files under `{copy.as_posix()}/`" in text
    assert "docs/results/equivariance/`" not in text


def test_the_plan_counts_a_deleted_cell(cli, copy):
    res = cli("study", "--plan", "--root", copy)
    assert res.exit_code == 0 and "0 cell(s) of trained runs to evaluate" in res.output, res.output
    rotated = sorted((copy / "rotated").rglob("*.json"))[0]
    table = sorted((copy / "cells").rglob("N*.json"))[0]
    rotated.unlink()
    table.unlink()
    res = cli("study", "--plan", "--root", copy)
    assert res.exit_code == 0 and "2 cell(s) of trained runs to evaluate" in res.output, res.output


def test_report_only_names_corrupt_cell_files(cli, tmp_path):
    """A truncated zero-shot cell and a corrupted rotated-world cell are named on one warning line each run; the
    report still comes out (they show as pending) and nothing raises."""
    root = tmp_path / "copy"
    shutil.copytree(ROOT, root)
    rotated = sorted((root / "rotated").rglob("*.json"))[0]
    table = sorted((root / "cells").rglob("N*.json"))[0]
    rotated.write_bytes(b"\xff\xfe not json")
    table.write_text(table.read_text()[:40])
    res = cli("study", "--report-only", "--root", root, "--report", tmp_path / "equivariance.md")
    assert res.exit_code == 0, res.output
    warning = [line for line in res.output.splitlines() if line.startswith("Warning:")]
    assert len(warning) == 1 and "2 cell file(s) cannot be read" in warning[0], res.output
    assert str(rotated) in warning[0] and str(table) in warning[0]
    assert "Traceback" not in res.output


def test_report_only_leaves_out_cells_of_replaced_weights_and_says_so(cli, tmp_path):
    """A checkpoint replaced by another training run (here: another arm's EGCBF+): its cells were computed with
    other weights, so the report leaves them out (pending) and the command names them."""
    root = tmp_path / "copy"
    shutil.copytree(ROOT, root)
    target = root / "checkpoints" / "no-closest" / "egcbf+"
    shutil.rmtree(target)
    shutil.copytree(root / "checkpoints" / "cpu-20" / "egcbf+", target)
    res = cli("study", "--report-only", "--root", root, "--report", tmp_path / "equivariance.md")
    assert res.exit_code == 0, res.output
    warning = [line for line in res.output.splitlines() if "computed with other weights" in line]
    assert len(warning) == 1 and str(root / "cells" / "no-closest") in warning[0], res.output
    assert "cpu-20" not in warning[0]
