"""Checkpoints: corrupted or mismatched files give a CheckpointError naming the file; best/ and the logs are
replaced atomically; resume falls back to the newest loadable checkpoint and says so."""

import csv
import json
import shutil

import pytest
import torch

from egcbf.io.atomic import recover_dir, replace_dir
from egcbf.train.checkpoint import (
    FORMAT_VERSION,
    CheckpointError,
    find_checkpoint,
    load_controller,
    load_learner,
    load_network,
)
from egcbf.train.loop import _truncate_csv, train


def _tiny_config(**changes):
    from egcbf.algo.config import TrainConfig

    return TrainConfig.preset("egcbf+", "tiny", steps=2, **changes)


@pytest.fixture
def run(tiny_run, tmp_path):
    dst = tmp_path / "run"
    shutil.copytree(tiny_run, dst)
    return dst


def _ckpt(run):
    """The newest checkpoint of ``run``."""
    return find_checkpoint(run)


def test_state_json_records_what_the_checkpoint_is(run):
    for d in (_ckpt(run), run / "best"):
        state = json.loads((d / "state.json").read_text())
        assert state["format_version"] == FORMAT_VERSION
        assert (state["algo"], state["group"], state["interface"]) == ("egcbf+", "se2xr", "accel")


@pytest.mark.parametrize(
    "name, content",
    [
        ("model.safetensors", b""),
        ("model.safetensors", b"not a safetensors file at all"),
        ("config.json", b'{"algo": "egcbf+", '),
        ("config.json", b"\xff\xfe\x00"),
        ("state.json", b"{"),
    ],
)
def test_corrupted_file_names_it(run, name, content):
    ckpt = _ckpt(run)
    (ckpt / name).write_bytes(content)
    with pytest.raises(CheckpointError, match=name.replace(".", r"\.")):
        load_controller(ckpt)


def test_truncated_weights_name_the_file(run):
    f = _ckpt(run) / "model.safetensors"
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    with pytest.raises(CheckpointError, match=r"model\.safetensors.*corrupted or truncated"):
        load_network(_ckpt(run), "policy")


def test_truncated_training_state_names_the_file(run):
    f = _ckpt(run) / "training_state.pt"
    f.write_bytes(f.read_bytes()[:100])
    with pytest.raises(CheckpointError, match=r"training_state\.pt"):
        load_learner(_ckpt(run))


def test_missing_weights_name_the_file(run):
    (run / "best" / "model.safetensors").unlink()
    with pytest.raises((CheckpointError, FileNotFoundError), match="best"):
        load_controller(run / "best")


@pytest.mark.parametrize("where", ["best", "newest"])
def test_missing_config_names_the_file(run, where):
    ckpt = run / "best" if where == "best" else _ckpt(run)
    (ckpt / "config.json").unlink()
    with pytest.raises(CheckpointError, match=r"config.json is missing.*holds weights"):
        load_controller(ckpt)


def test_another_methods_config_is_refused(run):
    from egcbf.algo.config import TrainConfig

    TrainConfig.preset("gcbf+", "tiny").to_json(run / "best" / "config.json")
    with pytest.raises(CheckpointError, match=r"algo 'egcbf\+'.*'gcbf\+'"):
        load_controller(run / "best")


def test_weights_of_another_shape_are_refused(run):
    from safetensors.torch import load_file

    from egcbf.train.checkpoint import read_config, save_weights, sha256

    f = run / "best" / "model.safetensors"
    w = load_file(str(f))
    key = next(k for k in w if k.startswith("policy."))
    w[key] = torch.zeros(3, 3, 3)
    save_weights(w, f, read_config(run / "best"))
    st = run / "best" / "state.json"
    st.write_text(json.dumps({**json.loads(st.read_text()), "weights_sha256": sha256(f)}))
    with pytest.raises(CheckpointError, match="does not match"):
        load_controller(run / "best")


def test_newer_format_is_refused(run):
    f = run / "best" / "state.json"
    state = json.loads(f.read_text())
    state["format_version"] = FORMAT_VERSION + 1
    f.write_text(json.dumps(state))
    with pytest.raises(CheckpointError, match="format"):
        load_controller(run / "best")


def test_resume_falls_back_past_a_corrupted_checkpoint_and_says_so(run):
    newest = _ckpt(run)
    assert newest.name == "step_000004"  # the tiny preset checkpoints every 2 updates
    (newest / "model.safetensors").write_bytes(b"broken")
    lines = []
    with pytest.warns(UserWarning, match="no replay buffers"):  # only the newest checkpoint keeps them
        learner = train(None, run, resume=True, steps=4, progress=False, log=lines.append)
    assert learner.step == 4
    assert any("cannot be loaded" in s and "step_000004" in s for s in lines)
    assert any("resuming from" in s and "step_000002" in s for s in lines)
    assert (run / "checkpoints" / "step_000004.corrupt").is_dir()
    assert find_checkpoint(run).name == "step_000004"
    load_learner(run)  # the new step 4 is complete
    with open(run / "metrics.csv", newline="") as f:
        assert [int(r["step"]) for r in csv.DictReader(f)] == [0, 2, 4]


def test_best_swap_killed_between_renames_is_recovered(tmp_path):
    best = tmp_path / "best"
    best.mkdir()
    (best / "state.json").write_text("old")
    # the state a kill between the two renames leaves: best.old complete, best.tmp complete, no best
    (tmp_path / "best.tmp").mkdir()
    (tmp_path / "best.tmp" / "state.json").write_text("new")
    best.rename(tmp_path / "best.old")
    assert recover_dir(best) == best and (best / "state.json").read_text() == "old"
    replace_dir(tmp_path / "best.tmp", best)
    assert (best / "state.json").read_text() == "new" and not (tmp_path / "best.old").exists()


def test_find_checkpoint_recovers_an_interrupted_best_swap(run):
    (run / "best").rename(run / "best.old")
    assert find_checkpoint(run / "best") == run / "best"
    load_controller(run / "best")


def test_truncating_a_log_drops_a_half_written_last_row(tmp_path):
    f = tmp_path / "scalars.csv"
    f.write_text("step,wall_s,tag,value\n1,0.1,a,1.0\n2,0.2,a,2.0\n3,0.3,a,3.0\n4,0.4\n")
    _truncate_csv(f, ("step", "wall_s", "tag", "value"), 3)
    with open(f, newline="") as fh:
        assert [r["step"] for r in csv.DictReader(fh)] == ["1", "2", "3"]
    assert not list(tmp_path.glob(".*tmp"))  # written through a temporary file, renamed over


def test_weights_of_another_run_are_refused(run, tmp_path):
    other = tmp_path / "other"
    train(_tiny_config(seed=7), other, progress=False, log=lambda s: None)
    shutil.copy(other / "best" / "model.safetensors", run / "best" / "model.safetensors")
    with pytest.raises(CheckpointError, match="SHA-256 differs"):
        load_controller(run / "best")


def test_state_json_records_the_weights_hash(run):
    from egcbf.train.checkpoint import sha256

    state = json.loads((run / "best" / "state.json").read_text())
    assert state["weights_sha256"] == sha256(run / "best" / "model.safetensors")


# ------------------------------------------------------------------------------ identity cannot be relabelled away
def _relabel(best, algo: str, group: str) -> None:
    """Edit what config.json and state.json say the weights are, consistently (the weights file untouched)."""
    cfg = json.loads((best / "config.json").read_text())
    cfg["algo"] = algo
    cfg["model"]["group"] = group
    (best / "config.json").write_text(json.dumps(cfg))
    st = json.loads((best / "state.json").read_text())
    st.update(algo=algo, group=group)
    (best / "state.json").write_text(json.dumps(st))


def test_weights_record_what_they_are_in_their_own_header(run):
    from egcbf.train.checkpoint import identity, read_config, weights_identity

    best = run / "best"
    assert weights_identity(best / "model.safetensors") == {k: str(v) for k, v in identity(read_config(best)).items()}


def test_relabelling_config_and_state_together_is_refused(run):
    """Editing both JSON files to call EGCBF+ weights GCBF+ is caught by the weights' own header."""
    _relabel(run / "best", "gcbf+", "trivial")
    with pytest.raises(CheckpointError, match=r"model.safetensors holds weights of algo 'egcbf\+'.*'gcbf\+'"):
        load_controller(run / "best")


def test_missing_state_json_is_fine_when_the_weights_say_what_they_are(run):
    (run / "best" / "state.json").unlink()
    load_controller(run / "best")  # identity from the weights' header: nothing to relabel
    from egcbf.algo.config import TrainConfig

    TrainConfig.preset("gcbf+", "tiny").to_json(run / "best" / "config.json")
    with pytest.raises(CheckpointError, match=r"holds weights of algo 'egcbf\+'"):
        load_controller(run / "best")


def _strip_header_identity(f) -> None:
    """Rewrite ``f`` as a format-1 file: the same tensors, no identity in the header."""
    from safetensors.torch import load_file, save_file

    save_file(load_file(str(f)), str(f))


def test_missing_state_json_of_legacy_weights_is_refused(run):
    """Weights written before format 2 say nothing about themselves: without state.json nothing can be checked."""
    _strip_header_identity(run / "best" / "model.safetensors")
    (run / "best" / "state.json").unlink()
    with pytest.raises(CheckpointError, match=r"state\.json is missing.*cannot be checked"):
        load_controller(run / "best")


@pytest.mark.parametrize("key", ["algo", "group", "interface", "weights_sha256"])
def test_legacy_state_json_stripped_of_a_key_is_refused(run, key):
    from egcbf.train.checkpoint import sha256

    best = run / "best"
    _strip_header_identity(best / "model.safetensors")
    st = json.loads((best / "state.json").read_text())
    st = {**st, "format_version": 1, "weights_sha256": sha256(best / "model.safetensors")}
    del st[key]
    (best / "state.json").write_text(json.dumps(st))
    with pytest.raises(CheckpointError, match=r"state\.json"):
        load_controller(best)


def test_legacy_checkpoint_with_complete_state_json_still_loads(run):
    from egcbf.train.checkpoint import sha256

    best = run / "best"
    _strip_header_identity(best / "model.safetensors")
    st = json.loads((best / "state.json").read_text())
    st.update(format_version=1, weights_sha256=sha256(best / "model.safetensors"))
    (best / "state.json").write_text(json.dumps(st))
    load_controller(best)


@pytest.mark.parametrize("load", [load_controller, load_learner, find_checkpoint], ids=lambda f: f.__name__)
@pytest.mark.parametrize("bad", [None, 3, ["best"]], ids=["None", "int", "list"])
def test_a_path_of_the_wrong_type_names_the_function_and_argument(load, bad):
    with pytest.raises(TypeError, match=rf"^{load.__name__}\(\) argument path must be a checkpoint or run directory "
                                        rf"\(str or pathlib.Path\), got {type(bad).__name__}$"):  # fmt: skip
        load(bad)
    with pytest.raises(TypeError, match=r"^load_network\(\) argument path"):
        load_network(bad, "policy")


def test_point_mass_weights_under_the_other_robots_config_are_refused(cli, tmp_path):
    """The single and double integrator's weights have the same shapes; what robot they drive is recorded beside
    them (state.json, and the weights' header for new checkpoints), so another robot's config.json is refused."""
    import shutil
    from pathlib import Path

    from rel_helpers import assert_usage_error
    from safetensors.torch import load_file

    from egcbf.train.checkpoint import CheckpointError, check_identity, read_config, save_weights, weights_identity

    root = Path(__file__).resolve().parents[2] / "checkpoints"
    ckpt = tmp_path / "ckpt"
    shutil.copytree(root / "double_integrator" / "egcbf+", ckpt)
    shutil.copy(root / "single_integrator" / "egcbf+" / "config.json", ckpt / "config.json")
    res = cli("eval", "--checkpoint", ckpt, "--num-agents", "4", "--episodes", "1", "--max-steps", "2",
              "--no-progress", "--out", tmp_path / "out")  # fmt: skip
    assert_usage_error(res, "robot", "double_integrator", "single_integrator")
    # weights written now carry the robot in their own header: caught without state.json too
    cfg = read_config(root / "double_integrator" / "egcbf+")
    save_weights(load_file(str(ckpt / "model.safetensors")), ckpt / "model.safetensors", cfg)
    assert weights_identity(ckpt / "model.safetensors")["robot"] == "double_integrator"
    (ckpt / "state.json").unlink()
    with pytest.raises(CheckpointError, match="robot 'double_integrator'"):
        check_identity(ckpt, read_config(ckpt))
