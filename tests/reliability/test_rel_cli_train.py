"""`egcbf train`, `demo` and `reproduce`: bad inputs and options that would be silently ignored are usage errors."""

import json
import shutil

import pytest
from rel_helpers import assert_usage_error


def _train(cli, out, *args):
    return cli("train", "--out", out, "--preset", "tiny", "--no-progress", *args)


@pytest.mark.parametrize(
    "args, phrases",
    [
        (["--algo", "ppo"], ["--algo", "ppo"]),
        (["--steps", "0"], ["--steps", ">= 1"]),
        (["--steps", "-4"], ["--steps", ">= 1"]),
        (["--threads", "-2"], ["--threads", ">= 1"]),
        (["--device", "foo"], ["--device", "foo"]),
        (["--preset", "huge"], ["--preset", "huge"]),
    ],
)
def test_bad_train_flag(cli, tmp_path, args, phrases):
    out = tmp_path / "run"
    assert_usage_error(_train(cli, out, *args), *phrases)
    assert not (out / "checkpoints").exists()


def test_train_config_file_missing(cli, tmp_path):
    assert_usage_error(_train(cli, tmp_path / "run", "--config", tmp_path / "nope.json"), "--config", "nope.json")


@pytest.mark.parametrize(
    "text, phrase",
    [("{not json", "--config"), ("[1, 2]", "JSON object"), ('{"bogus": 1}', "bogus"), ('{"lr_cbf": -1}', "lr_cbf")],
)
def test_train_config_file_bad(cli, tmp_path, text, phrase):
    cfg = tmp_path / "cfg.json"
    cfg.write_text(text)
    assert_usage_error(_train(cli, tmp_path / "run", "--config", cfg), phrase)


def test_train_config_algo_conflict(cli, tmp_path):
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"algo": "gcbf"}))
    assert_usage_error(_train(cli, tmp_path / "run", "--config", cfg, "--algo", "egcbf+"), "--config", "--algo")


def test_train_out_is_a_file(cli, tmp_path):
    f = tmp_path / "run"
    f.write_text("x")
    assert_usage_error(_train(cli, f), "--out", "is a file")


def test_fresh_train_into_a_run_is_refused(cli, tiny_run):
    assert_usage_error(_train(cli, tiny_run), "--out", "--resume")


@pytest.fixture
def run_copy(tiny_run, tmp_path):
    dst = tmp_path / "run"
    shutil.copytree(tiny_run, dst)
    return dst


@pytest.mark.parametrize(
    "args, phrases",
    [
        (["--algo", "gcbf+"], ["--algo", "resume"]),
        (["--algo", "egcbf+"], ["--algo", "resume"]),  # even the run's own method: it would be ignored
        (["--seed", "3"], ["--resume", "--steps"]),
        (["--preset", "cpu"], ["--resume"]),
        (["--device", "cpu"], ["--resume"]),
        (["--steps", "3"], ["--steps 3", "current update 4"]),
        (["--steps", "0"], ["--steps", ">= 1"]),
    ],
)
def test_resume_refuses_ignored_or_bad_options(cli, run_copy, args, phrases):
    res = cli("train", "--out", run_copy, "--resume", "--no-progress", *args)
    assert_usage_error(res, *phrases)


def test_resume_without_a_run(cli, tmp_path):
    assert_usage_error(cli("train", "--out", tmp_path / "none", "--resume", "--no-progress"), "no checkpoint")


def test_resume_with_every_checkpoint_corrupted_names_them(cli, run_copy):
    for f in (run_copy / "checkpoints").glob("step_*/model.safetensors"):
        f.write_bytes(b"garbage")
    res = cli("train", "--out", run_copy, "--resume", "--no-progress")
    assert_usage_error(res, "model.safetensors", "corrupted")


# ------------------------------------------------------------------------------------------------ demo
@pytest.mark.parametrize(
    "args, phrases",
    [
        (["--method", "nope"], ["unknown method", "nope"]),
        (["--baseline", "nope"], ["unknown method", "nope"]),
        (["--episodes", "0"], ["--episodes"]),
        (["--num-agents", "0"], ["--num-agents"]),
        (["--num-agents", "5000", "--area", "1"], ["--num-agents 5000", "--area"]),
        (["--area", "-2"], ["--area"]),
        (["--device", "gpu0"], ["--device"]),
        (["--obstacles", "-1"], ["--obstacles"]),
    ],
)
def test_bad_demo_flag(cli, tmp_path, args, phrases):
    out = tmp_path / "demo"
    res = cli("demo", "--method", "ccbf", "--out", out, "--no-progress", "--max-steps", "3", "--episodes", "1", *args)
    assert_usage_error(res, *phrases)
    assert not (out / "demo.json").exists()


def test_demo_without_checkpoints_names_the_folder(cli, tmp_path):
    res = cli("demo", "--checkpoints", tmp_path / "ck", "--out", tmp_path / "demo", "--no-progress")
    assert_usage_error(res, "--checkpoints", "egcbf+")


def test_demo_with_a_corrupted_checkpoint_names_the_file(cli, tmp_path, tiny_run):
    root = tmp_path / "ck"
    shutil.copytree(tiny_run / "best", root / "egcbf+")
    (root / "egcbf+" / "model.safetensors").write_bytes(b"\x10\x00")
    res = cli("demo", "--checkpoints", root, "--baseline", "none", "--out", tmp_path / "demo", "--no-progress")
    assert_usage_error(res, "model.safetensors")


def test_demo_refuses_a_folder_with_results(cli, tmp_path):
    out = tmp_path / "demo"
    args = ["demo", "--method", "ccbf", "--out", out, "--no-progress", "--max-steps", "2", "--episodes", "1"]
    args += ["--num-agents", "4", "--obstacles", "0"]
    assert cli(*args).exit_code == 0
    assert_usage_error(cli(*args), "--out", "--overwrite")
    assert cli(*args, "--overwrite").exit_code == 0


# ------------------------------------------------------------------------------------------------ reproduce
@pytest.mark.parametrize(
    "args, phrases",
    [
        (["--methods", "gcbf,bogus"], ["--methods", "bogus"]),
        (["--obstacle-methods", "x"], ["--obstacle-methods"]),
        (["--num-agents", "0"], ["--num-agents"]),
        (["--num-agents", "8,100000", "--area", "1"], ["--num-agents 100000"]),
        (["--episodes", "0"], ["episodes"]),
        (["--workers", "0"], ["workers"]),
        (["--backend", "mpi"], ["backend"]),
        (["--device", "foo"], ["--device"]),
        (["--max-steps", "0"], ["max"]),
    ],
)
def test_bad_reproduce_flag(cli, tmp_path, args, phrases):
    out = tmp_path / "rep"
    res = cli("reproduce", "--methods", "nominal", "--obstacle-methods", "nominal", "--out", out,
              "--report", tmp_path / "r.md", "--no-progress", *args)  # fmt: skip
    assert_usage_error(res, *phrases)
    assert not (tmp_path / "r.md").exists()


def test_reproduce_out_that_is_a_file_is_refused(cli, tmp_path):
    f = tmp_path / "cells"
    f.write_text("x")
    res = cli("reproduce", "--methods", "nominal", "--obstacle-methods", "nominal", "--out", f,
              "--report", tmp_path / "r.md", "--no-progress", "--episodes", "1", "--max-steps", "2")  # fmt: skip
    assert_usage_error(res, "--out", "is a file")


def test_reproduce_report_in_a_file_is_refused(cli, tmp_path):
    f = tmp_path / "notadir"
    f.write_text("x")
    res = cli("reproduce", "--methods", "nominal", "--obstacle-methods", "nominal", "--out", tmp_path / "cells",
              "--report", f / "r.md", "--no-progress", "--episodes", "1", "--max-steps", "2")  # fmt: skip
    assert_usage_error(res, "--report", "is a file")


def test_resume_falls_back_past_a_corrupted_checkpoint_and_says_so(cli, run_copy):
    newest = sorted((run_copy / "checkpoints").glob("step_*"))[-1]
    (newest / "training_state.pt").write_bytes(b"truncated")
    res = cli("train", "--out", run_copy, "--resume", "--no-progress")
    assert res.exit_code == 0, res.output
    assert "cannot be loaded" in res.output and "training_state.pt" in res.output
    assert "resuming from" in res.output and "step_000002" in res.output


# ------------------------------------------------------------------------------------------------ memory estimates
def test_training_that_cannot_fit_is_refused_with_the_number(cli, tmp_path, monkeypatch):
    from egcbf.cli import checks as cli_checks

    monkeypatch.setattr(cli_checks, "available_memory", lambda device: 2**20)  # 1 MiB left
    out = tmp_path / "run"
    res = cli("train", "--algo", "egcbf+", "--steps", "1", "--out", out, "--no-progress")  # the cpu recipe
    assert_usage_error(res, "training needs about", "MiB", "1.0 MiB available", "batch_size")
    assert not (out / "config.json").exists()


def test_training_that_fits_is_not_refused():
    from egcbf.algo.config import TrainConfig
    from egcbf.cli import checks as cli_checks

    cli_checks.check_training_memory(TrainConfig.preset("egcbf+", "cpu"), cli_checks.parse_device("cpu"))


def test_sweep_that_cannot_fit_is_refused_with_the_number(cli, tmp_path, monkeypatch, tiny_run):
    from egcbf.cli import checks as cli_checks

    root = tmp_path / "ck"
    shutil.copytree(tiny_run / "best", root / "egcbf+")
    monkeypatch.setattr(cli_checks, "available_memory", lambda device: 2**20)
    res = cli("reproduce", "--methods", "egcbf+", "--obstacle-methods", "egcbf+", "--num-agents", "64,128",
              "--train-seeds", "0", "--scale-sizes", "none", "--checkpoints", root, "--out", tmp_path / "cells",
              "--report", tmp_path / "r.md", "--no-progress")  # fmt: skip
    assert_usage_error(res, "largest learned cell (N = 128", "--workers")
    assert not (tmp_path / "cells").exists()


# ------------------------------------------------------------------------------------------------ labels and lists
@pytest.fixture(scope="module")
def gcbf_plus_run(tmp_path_factory):
    """A finished ``tiny`` GCBF+ run of 2 updates (the other method's weights, for the swapped-folders case)."""
    from egcbf.algo.config import TrainConfig
    from egcbf.train.loop import train

    out = tmp_path_factory.mktemp("gcbf_plus_run")
    train(TrainConfig.preset("gcbf+", "tiny", steps=2), out, progress=False, log=lambda s: None)
    return out


def test_demo_with_swapped_method_folders_is_refused_not_mislabelled(cli, tmp_path, tiny_run, gcbf_plus_run):
    """GCBF+ weights under checkpoints/egcbf+ (and EGCBF+ weights under gcbf+) are never labelled "EGCBF+ (learned,
    equivariant)": the label comes from the weights' own header, also when config.json and state.json are
    relabelled to match the folder."""
    root = tmp_path / "ck"
    shutil.copytree(gcbf_plus_run / "best", root / "egcbf+")
    shutil.copytree(tiny_run / "best", root / "gcbf+")
    args = ["--compare", "gcbf+", "--num-agents", "3", "--area", "1.5", "--obstacles", "0", "--episodes", "1"]
    res = cli("demo", "--checkpoints", root, "--out", tmp_path / "demo", "--no-progress", "--max-steps", "3", *args)
    assert_usage_error(res, "holds gcbf+ weights", "not egcbf+", str(root / "egcbf+"))
    assert not (tmp_path / "demo").exists()
    best = root / "egcbf+"  # relabel the GCBF+ checkpoint's JSON files to say EGCBF+, consistently
    group = json.loads((tiny_run / "best" / "config.json").read_text())["model"]["group"]
    cfg = json.loads((best / "config.json").read_text())
    cfg["algo"], cfg["model"]["group"] = "egcbf+", group
    (best / "config.json").write_text(json.dumps(cfg))
    st = json.loads((best / "state.json").read_text())
    st.update(algo="egcbf+", group=group)
    (best / "state.json").write_text(json.dumps(st))
    res = cli("demo", "--checkpoints", root, "--out", tmp_path / "demo", "--no-progress", "--max-steps", "3", *args)
    assert_usage_error(res, "model.safetensors holds weights of algo 'gcbf+'")
    assert not (tmp_path / "demo").exists()


_REPRO_TINY = ["--area", "1.5", "--episodes", "1", "--max-steps", "2", "--train-seeds", "0", "--scale-sizes", "none",
               "--no-progress"]  # fmt: skip


@pytest.mark.parametrize(
    ("flag", "value", "extra"),
    [("--obstacle-methods", "nominal,dcbf", "dcbf"), ("--seed-methods", "egcbf+", "egcbf+"),
     ("--scale-methods", "nominal,ccbf", "ccbf")],
)  # fmt: skip
def test_reproduce_method_lists_naming_a_method_not_run_are_refused(cli, tmp_path, flag, value, extra):
    """An entry of --obstacle-methods / --seed-methods / --scale-methods that --methods does not run is refused,
    naming it (it used to be dropped silently)."""
    res = cli("reproduce", "--methods", "nominal", flag, value, "--num-agents", "2", "--out", tmp_path / "cells",
              "--report", tmp_path / "r.md", "--checkpoints", tmp_path / "ck", *_REPRO_TINY)  # fmt: skip
    assert_usage_error(res, f"{flag} names {extra}", "which --methods does not run", "--methods nominal")
    assert not (tmp_path / "r.md").exists() and not (tmp_path / "cells").exists()


def test_reproduce_report_only_names_a_truncated_cell_file(cli, tmp_path):
    """--report-only over a cell file cut short (a kill or a full disk during a copy) names it instead of skipping
    it silently."""
    args = ["reproduce", "--methods", "nominal", "--obstacle-methods", "nominal", "--num-agents", "2,3", "--obstacles",
            "0", "--out", tmp_path / "cells", "--report", tmp_path / "r.md", *_REPRO_TINY]  # fmt: skip
    res = cli(*args)
    assert res.exit_code == 0, res.output
    victim = tmp_path / "cells" / "nominal_obs0" / "N3.json"
    victim.write_text(victim.read_text()[:40])
    res = cli(*args, "--report-only")
    assert res.exit_code == 0, res.output
    warnings = [line for line in res.output.splitlines() if line.startswith("Warning:")]
    assert len(warnings) == 1 and "1 cell file(s) cannot be read" in warnings[0], res.output
    assert str(victim) in warnings[0] and "Traceback" not in res.output
