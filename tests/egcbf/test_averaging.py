"""Weight averaging of two checkpoints (egcbf.train.averaging, ``egcbf average``): the end points are the inputs, the
result is the same model and stays SE2xR-equivariant, its provenance is recorded, and bad inputs are refused."""

import functools
import json
from pathlib import Path

import pytest
import torch
from dyn_helpers import moving_scene
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from egcbf.cli import app
from egcbf.env import EnvConfig
from egcbf.env.graph import GROUP, build_graph
from egcbf.train.averaging import average_checkpoints, average_weights
from egcbf.train.checkpoint import CheckpointError, load_network, read_config, read_tensors, sha256
from groupcanon import FieldType
from groupcanon.features import Vector
from groupcanon.testing import strategies as gst

CKPTS = Path(__file__).resolve().parents[2] / "checkpoints"
ROOT = CKPTS / "paper-target"
# A fine-tuned from B (A's config records B's weights as its start); UNRELATED: another run of the same model
A, B, OTHER = CKPTS / "fine-tuned" / "egcbf+", ROOT / "egcbf+", ROOT / "gcbf+"
UNRELATED = ROOT / "seeds" / "egcbf+-s1"

pytestmark = pytest.mark.skipif(not A.exists() or not B.exists(), reason="no paper-target checkpoints")


@pytest.mark.parametrize("lam, source", [(1.0, A), (0.0, B)])
def test_the_end_points_are_the_inputs(tmp_path, lam, source):
    out = average_checkpoints(A, B, lam, tmp_path / "avg")
    got, want = read_tensors(out / "model.safetensors"), read_tensors(source / "model.safetensors")
    assert got.keys() == want.keys() and all(torch.equal(got[k], want[k]) for k in got)


def test_the_average_is_elementwise_and_records_its_inputs(tmp_path):
    out = average_checkpoints(A, B, 0.3, tmp_path / "avg")
    a, b, m = (read_tensors(p / "model.safetensors") for p in (A, B, out))
    for k in m:
        assert torch.allclose(m[k].double(), 0.3 * a[k].double() + 0.7 * b[k].double(), rtol=0, atol=1e-6), k
    state = json.loads((out / "state.json").read_text())
    rec = state["weight_average"]
    assert rec["lam"] == 0.3 and rec["a_sha256"] == sha256(A / "model.safetensors")
    assert rec["b_sha256"] == sha256(B / "model.safetensors") and state["weights_sha256"] == sha256(
        out / "model.safetensors"
    )
    assert read_config(out) == read_config(A)
    again = read_tensors(average_checkpoints(A, B, 0.3, tmp_path / "again") / "model.safetensors")
    assert all(torch.equal(again[k], m[k]) for k in m)  # rebuilt exactly (the header's key order may differ)


@functools.cache
def _averaged_policy(lam: float):
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        return load_network(average_checkpoints(A, B, lam, Path(d) / "avg"), "policy", dtype=torch.float64)[0]


@given(g=gst.elements(GROUP, batch=(2,)), seed=st.integers(0, 2**20), lam=st.sampled_from([0.25, 0.5]))
@settings(max_examples=10, deadline=None)
def test_the_averaged_egcbf_policy_is_equivariant(g, seed, lam):
    """Averaging two SE2xR-equivariant policies gives an equivariant one (the canonicalization does not depend on the
    weights): the command rotates with the scene, float64 to 1e-9."""
    cfg = EnvConfig(num_agents=5, num_envs=2, n_rays=8, lidar_max_hits=4, area_size=1.2, num_obstacles=2)
    pol = _averaged_policy(lam)
    rotate = FieldType(GROUP, [Vector(3)])
    state = moving_scene(cfg, seed)
    with torch.no_grad():
        a = pol(build_graph(state, cfg)).view(2, 5, 3)
        b = pol(build_graph(state.transform(g), cfg)).view(2, 5, 3)
    assert (rotate.act(g[:, None].expand(2, 5, 5), a) - b).abs().max() <= 1e-9


def test_bad_inputs_are_refused(tmp_path):
    with pytest.raises(CheckpointError, match="not the same model"):
        average_checkpoints(A, OTHER, 0.5, tmp_path / "x")
    with pytest.raises(CheckpointError, match=r"lam must be in \[0, 1\]"):
        average_checkpoints(A, B, 1.5, tmp_path / "x")
    with pytest.raises(CheckpointError, match="one of the checkpoints"):
        average_checkpoints(A, B, 0.5, B)
    with pytest.raises(CheckpointError, match="one of the checkpoints"):  # a directory holding an input
        average_checkpoints(A, B, 0.5, B.parent)
    keep = tmp_path / "runs"
    (keep / "important").mkdir(parents=True)
    with pytest.raises(CheckpointError, match="not a checkpoint directory"):
        average_checkpoints(A, B, 0.5, keep)
    assert (keep / "important").is_dir()  # nothing was deleted
    assert not (tmp_path / "x").exists()
    with pytest.raises(CheckpointError, match=r"not one training lineage.*--allow-unrelated"):
        average_checkpoints(A, UNRELATED, 0.5, tmp_path / "x")
    assert not (tmp_path / "x").exists()
    assert (average_checkpoints(A, UNRELATED, 0.5, tmp_path / "x", allow_unrelated=True) / "model.safetensors").exists()
    with pytest.raises(ValueError, match="different tensors"):
        average_weights({"w": torch.zeros(2)}, {"v": torch.zeros(2)}, 0.5)
    with pytest.raises(ValueError, match="cannot average"):
        average_weights({"w": torch.zeros(2)}, {"w": torch.zeros(3)}, 0.5)


def test_the_command(tmp_path):
    out = tmp_path / "avg"
    args = ["average", "--a", str(A), "--b", str(B), "--lam", "0.5", "--out", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0 and "0.5 x" in res.output and (out / "model.safetensors").exists()
    res = CliRunner().invoke(app, args)  # never overwrites a checkpoint silently
    assert res.exit_code == 2 and "--overwrite" in res.output
    assert CliRunner().invoke(app, [*args, "--overwrite"]).exit_code == 0
    res = CliRunner().invoke(app, ["average", "--a", str(A), "--b", str(B), "--lam", "-0.1", "--out", str(out)])
    assert res.exit_code == 2 and "--lam must be in [0, 1]" in res.output
    res = CliRunner().invoke(
        app, ["average", "--a", str(A), "--b", str(OTHER), "--lam", "0.5", "--out", str(tmp_path / "z")]
    )
    assert res.exit_code == 2 and "not the same model" in res.output
    unrelated = ["average", "--a", str(A), "--b", str(UNRELATED), "--lam", "0.5", "--out", str(tmp_path / "u")]
    res = CliRunner().invoke(app, unrelated, env={"COLUMNS": "400"})
    assert res.exit_code == 2 and "not one training lineage" in res.output and not (tmp_path / "u").exists()
    assert CliRunner().invoke(app, [*unrelated, "--allow-unrelated"]).exit_code == 0
