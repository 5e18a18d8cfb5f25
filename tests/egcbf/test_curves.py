"""Training curves from metrics.csv files."""

import csv
import json

import pytest

from egcbf.viz.curves import load_metrics, training_curves


def _write_run(d, rows, best_step=None):
    d.mkdir(parents=True)
    with open(d / "metrics.csv", "w", newline="") as f:
        w = csv.DictWriter(f, ["step", "wall_s", "safe_rate", "reach_rate", "success_rate", "cost"])
        w.writeheader()
        w.writerows(rows)
    if best_step is not None:
        (d / "state.json").write_text(json.dumps({"step": best_step}))


def test_load_metrics_sorts_by_step_and_keeps_rates(tmp_path):
    rows = [
        {"step": 10, "wall_s": 20.0, "safe_rate": 0.9, "reach_rate": 1.0, "success_rate": 0.9, "cost": 0.1},
        {"step": 0, "wall_s": 1.0, "safe_rate": 0.8, "reach_rate": 1.0, "success_rate": 0.8, "cost": 0.2},
    ]
    _write_run(tmp_path / "a", rows)
    m = load_metrics(tmp_path / "a")
    assert m["step"] == [0.0, 10.0] and m["safe_rate"] == [0.8, 0.9] and "cost" not in m
    with pytest.raises(FileNotFoundError, match="egcbf train"):
        load_metrics(tmp_path / "missing")


def test_training_curves_writes_a_png(tmp_path):
    rows = [
        {"step": s, "wall_s": 5.0 * s, "safe_rate": 0.8 + s / 100, "reach_rate": 1.0, "success_rate": 0.8, "cost": 0}
        for s in (0, 5, 10)
    ]
    _write_run(tmp_path / "a", rows, best_step=5)
    _write_run(tmp_path / "b", rows)
    out = training_curves({"A": tmp_path / "a", "B": tmp_path / "b"}, tmp_path / "fig" / "c.png")
    assert out.exists() and out.read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(ValueError):
        training_curves({}, tmp_path / "x.png")


def test_training_curves_of_several_seeds_average_on_common_steps(tmp_path):
    from egcbf.viz.curves import _on_grid

    def rows(level, steps):
        return [{"step": s, "wall_s": 2.0 * s, "safe_rate": level, "reach_rate": 1.0, "success_rate": level,
                 "cost": 0} for s in steps]  # fmt: skip

    _write_run(tmp_path / "s0", rows(0.6, (0, 10, 20)))
    _write_run(tmp_path / "s1", rows(0.8, (0, 10)))  # stopped earlier: only the common steps are averaged
    data = [load_metrics(tmp_path / "s0"), load_metrics(tmp_path / "s1")]
    steps, mean, lo, hi, wall = _on_grid(data, "safe_rate")
    assert steps == [0.0, 10.0] and mean == pytest.approx([0.7, 0.7]) and lo == [0.6, 0.6] and hi == [0.8, 0.8]
    assert wall == [0.0, 20.0]
    out = training_curves({"A": [tmp_path / "s0", tmp_path / "s1"], "B": tmp_path / "s0"}, tmp_path / "m.png")
    assert out.read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(ValueError, match="at least one run"):
        training_curves({"A": []}, tmp_path / "x.png")
