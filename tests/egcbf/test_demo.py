"""`egcbf demo`: the learned method beside its baseline on the same seeds (tiny checkpoints, short episodes)."""

import json

import pytest
from PIL import Image
from typer.testing import CliRunner

from egcbf.algo.config import TrainConfig
from egcbf.cli import app
from egcbf.io.report import number, pct
from egcbf.train.loop import train

SMALL = ["--num-agents", "3", "--area", "1.5", "--obstacles", "1", "--episodes", "1", "--max-steps", "8"]


def _invoke(args):
    return CliRunner().invoke(app, ["demo", "--no-progress", *args], env={"COLUMNS": "400"})


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    root = tmp_path_factory.mktemp("checkpoints")
    for algo in ("egcbf+", "gcbf+"):  # run directories: the demo takes their newest checkpoint
        train(TrainConfig.preset(algo, "tiny", steps=1), root / algo, progress=False, log=lambda s: None)
    return root


def test_demo_compares_five_controllers_on_the_same_episodes(checkpoints, tmp_path):
    out = tmp_path / "demo"
    res = _invoke(["--checkpoints", str(checkpoints), "--out", str(out), *SMALL])
    assert res.exit_code == 0, res.output
    names = ("egcbf+", "egcbf+:dcbf", "gcbf+", "nominal", "dcbf")
    for name in names:
        rows = json.loads((out / name.replace(":", "_") / "metrics.json").read_text())
        assert [r["num_agents"] for r in rows] == [3] and rows[0]["num_episodes"] == 1
        assert not list((out / name).glob("*.gif"))  # one comparison GIF instead of one per controller
    gif = Image.open(out / "compare_N3.gif")
    assert gif.format == "GIF" and gif.n_frames == 9  # the start and every step of the 8-step episode
    assert (out / "egcbf+_N3_topdown.png").stat().st_size > 0
    summary = json.loads((out / "demo.json").read_text())
    assert summary["method"] == "egcbf+" and summary["compared"] == ["egcbf+:dcbf", "gcbf+", "nominal", "dcbf"]
    assert json.loads((out / "egcbf+_dcbf" / "run.json").read_text())["filter"] == "dcbf"
    assert list(summary["metrics"]) == list(names) and summary["num_agents"] == 3
    table = (out / "summary.md").read_text()
    for label in ("EGCBF+ (learned, equivariant)", "EGCBF+ + dCBF filter", "GCBF+ (learned)", "nominal (no safety",
                  "dCBF-QP"):  # fmt: skip
        assert label in table and label in res.output
    line = next(ln for ln in table.splitlines() if ln.startswith("nominal"))
    nominal = summary["metrics"]["nominal"]
    assert line.split()[-5:] == [pct(nominal[k]) for k in ("safe_rate", "reach_rate", "success_rate")] + [
        number(nominal["cost"]), f"{nominal['step_ms_median']:.2f}"]  # fmt: skip


def test_comparison_gif_marks_agents_that_collided(tmp_path):
    import numpy as np

    from egcbf.viz.render import render_comparison_gif

    traj = np.array([[1.0, 1.0, 1.0], [3.0, 3.0, 1.0]]) + 0.2 * np.arange(5)[:, None, None] * np.array([1, 0, 0])
    hit = np.zeros((5, 2), dtype=bool)
    hit[2, 0] = True
    path = render_comparison_gif(tmp_path / "c.gif", {"a": (traj, hit), "b": (traj, np.zeros_like(hit))},
                                 area_size=4.0, max_frames=5)  # fmt: skip
    frames = Image.open(path)
    assert frames.n_frames == 5
    frames.seek(4)
    rgb = np.asarray(frames.convert("RGB")).astype(int)
    red = (rgb[..., 0] > 200) & (rgb[..., 1] < 80) & (rgb[..., 2] < 80)
    half = rgb.shape[1] // 2
    assert red[:, :half].any() and not red[:, half:].any()  # the ring stays on the agent of panel a after the hit
    with pytest.raises(ValueError, match="same"):
        render_comparison_gif(tmp_path / "d.gif", {"a": (traj, hit), "b": (traj[:3], hit[:3])})


def test_demo_names_a_missing_checkpoint_and_how_to_train_it(tmp_path):
    missing = tmp_path / "nothing-here"
    res = _invoke(["--checkpoints", str(missing), "--out", str(tmp_path / "o"), *SMALL])
    assert res.exit_code != 0
    assert str(missing / "egcbf+") in res.output and "egcbf train --algo egcbf+" in res.output
    assert not (tmp_path / "o").exists()  # failed before any work


def test_demo_with_a_missing_baseline_fails_before_evaluating(checkpoints, tmp_path):
    res = _invoke(["--checkpoints", str(checkpoints), "--compare", "gcbf", "--out", str(tmp_path / "o"), *SMALL])
    assert res.exit_code != 0 and "egcbf train --algo gcbf " in res.output
    assert not (tmp_path / "o").exists()


def test_demo_runs_a_hand_crafted_controller_without_checkpoints(tmp_path):
    out = tmp_path / "demo"
    res = _invoke(["--method", "ccbf", "--checkpoints", str(tmp_path / "none"), "--out", str(out), *SMALL])
    assert res.exit_code == 0, res.output
    assert (out / "ccbf" / "metrics.json").exists() and (out / "compare_N3.gif").exists()
    assert json.loads((out / "demo.json").read_text())["compared"] == ["nominal"]


def test_demo_rejects_an_unknown_method(tmp_path):
    res = _invoke(["--method", "nope", "--out", str(tmp_path / "o"), *SMALL])
    assert res.exit_code != 0 and "unknown method" in res.output


def test_demo_labels_come_from_the_weights_not_the_folder_names(checkpoints, tmp_path):
    """Method folders swapped: GCBF+ weights under checkpoints/egcbf+ are refused, not labelled EGCBF+."""
    import shutil

    swapped = tmp_path / "swapped"
    shutil.copytree(checkpoints / "egcbf+", swapped / "gcbf+")
    shutil.copytree(checkpoints / "gcbf+", swapped / "egcbf+")
    res = _invoke(["--checkpoints", str(swapped), "--compare", "gcbf+", "--out", str(tmp_path / "o"), *SMALL])
    assert res.exit_code == 2 and "holds gcbf+ weights" in res.output and "not egcbf+" in res.output, res.output
    assert not (tmp_path / "o").exists()
