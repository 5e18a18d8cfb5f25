"""``egcbf robustness`` reads only the cells of the checkpoints it names: a cell computed with other weights than the
ones now under ``--checkpoints`` is stale, left out of the report, and the report says so (never "all cells
computed ... the shipped checkpoints" from cells whose stored sha256 no longer matches)."""

from pathlib import Path

from egcbf.reproduce.plan import cell_key
from egcbf.reproduce.store import find_method_checkpoint, write_json
from egcbf.robustness import RobustnessConfig, axis, write_report
from egcbf.robustness.cells import _cell, load_records, stale_records

CHECKPOINTS = Path(__file__).resolve().parents[2] / "checkpoints"


def _store(cfg, spec, sha):
    cell = _cell("egcbf+", spec, 4, 0)
    key = cell_key(cfg.sweep(spec, ("egcbf+",)), cell, sha)
    row = {"safe_rate": 1.0, "success_rate": 1.0, "safe_episodes": [1.0, 1.0], "success_episodes": [1.0, 1.0]}
    write_json(cell.path(cfg.out), {"key": key, "row": row, "meta": {}})


def test_cells_of_another_checkpoint_are_stale_and_left_out_of_the_report(tmp_path):
    cfg = RobustnessConfig(axes=("field",), controllers=("egcbf+",), num_agents=(4,), episodes=2,
                           out=tmp_path / "cells", checkpoints=CHECKPOINTS)  # fmt: skip
    spec = axis("field").specs()[0]
    current = find_method_checkpoint(CHECKPOINTS, "egcbf+", 0).sha256
    _store(cfg, spec, current)
    assert not stale_records(cfg, load_records(cfg))
    _store(cfg, spec, "0" * 64)  # the same cell, computed with weights that are no longer the shipped ones
    records = load_records(cfg)
    assert list(stale_records(cfg, records).values()) == ["0" * 64]
    report = write_report(cfg, tmp_path / "robustness.md", tmp_path / "fig").read_text()
    assert "0 of 4 cells computed; 1 more computed with a checkpoint other than the one now in" in report
    assert "left out as stale" in report and "all 4 cells computed" not in report


def test_report_only_names_a_corrupt_cell_file(cli, tmp_path):
    cfg = RobustnessConfig(axes=("field",), controllers=("egcbf+",), num_agents=(4,), episodes=2,
                           out=tmp_path / "cells", checkpoints=CHECKPOINTS)  # fmt: skip
    spec = axis("field").specs()[0]
    _store(cfg, spec, find_method_checkpoint(CHECKPOINTS, "egcbf+", 0).sha256)
    path = _cell("egcbf+", spec, 4, 0).path(cfg.out)
    path.write_text(path.read_text()[:25])  # truncated
    res = cli("robustness", "--report-only", "--axes", "field", "--controllers", "egcbf+", "--num-agents", "4",
              "--episodes", "2", "--out", cfg.out, "--checkpoints", CHECKPOINTS, "--report", tmp_path / "r.md",
              "--figures", tmp_path / "fig")  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "Warning: 1 cell file(s) cannot be read" in res.output and str(path) in res.output, res.output
    assert "0 of 4 cells computed" in (tmp_path / "r.md").read_text()
