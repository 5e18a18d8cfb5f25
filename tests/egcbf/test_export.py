"""egcbf.deploy.export / ``egcbf export``: the exported files (TorchScript, ONNX) compute what the per-agent PyTorch
controller computes on every agent of random scenes (float32, 1e-5), ONNX runs under onnxruntime with neither torch
nor egcbf imported, masked rows change nothing, and the files carry their layout."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from egcbf.cli import app
from egcbf.deploy.agent import AgentController
from egcbf.deploy.export import INPUT_NAMES, OUTPUT_NAMES, export_controller, run_onnx
from egcbf.env import EnvConfig, SwarmEnv

onnxruntime = pytest.importorskip("onnxruntime")
ROOT = Path(__file__).resolve().parents[2] / "checkpoints"
MAX_NEIGHBOURS, MAX_HITS = 6, 8
TOL = 1e-5  # float32: the exported graph sums in another order than the eager module


@pytest.fixture(scope="module", params=["egcbf+", "gcbf+"])
def exported(request, tmp_path_factory):
    """``(controller, {format: path})`` of one shipped method, exported once for the module."""
    ctrl = AgentController.from_checkpoint(ROOT / request.param, max_neighbours=MAX_NEIGHBOURS, max_hits=MAX_HITS)
    out = tmp_path_factory.mktemp(request.param.replace("+", "p"))
    files = {
        fmt: export_controller(ctrl, fmt, out / f"agent.{fmt}", ROOT / request.param) for fmt in ("onnx", "torchscript")
    }
    return ctrl, files


def _observations(ctrl: AgentController, seed: int, n: int, area: float, obstacles: int):
    """Every agent's padded observation in a random scene (moved a few steps by the policy's swarm)."""
    cfg = EnvConfig.for_robot("quadrotor", num_agents=n, area_size=area, num_obstacles=obstacles, num_envs=1)
    env = SwarmEnv(cfg, dtype=torch.float32)
    state = env.reset(seed)
    lidar = env.lidar(state)
    for i in range(n):
        others = torch.cat((state.x[0, :i], state.x[0, i + 1 :]))
        hits = lidar.points[0, i][lidar.valid[0, i]]
        yield ctrl.pad(state.x[0, i], state.goals[0, i], others, hits)


@given(seed=st.integers(0, 2**16), n=st.integers(1, 12), area=st.floats(0.8, 2.5), obstacles=st.integers(0, 3))
@settings(max_examples=5, deadline=None)
def test_the_files_compute_the_per_agent_controller(exported, seed, n, area, obstacles):
    ctrl, files = exported
    ts = torch.jit.load(str(files["torchscript"]))
    for inputs in _observations(ctrl, seed, n, area, obstacles):
        with torch.no_grad():
            want = ctrl.module(*inputs)
            got_ts = ts(*inputs)
        got_onnx = run_onnx(files["onnx"], inputs)
        for name, w, a, b in zip(OUTPUT_NAMES, want, got_ts, got_onnx):
            assert (a - w).abs().max() <= TOL, name
            assert np.abs(b - w.numpy()).max() <= TOL, name


def test_masked_rows_change_nothing(exported):
    ctrl, files = exported
    inputs = list(next(_observations(ctrl, 3, 8, 1.2, 2)))
    base = run_onnx(files["onnx"], inputs)
    nbr, nbr_valid, hits, hit_valid = inputs[2].clone(), inputs[3], inputs[4].clone(), inputs[5]
    nbr[~nbr_valid] = torch.randn_like(nbr[~nbr_valid]) * 0.1  # garbage in the unused rows, some within range
    hits[~hit_valid] = torch.randn_like(hits[~hit_valid]) * 0.1
    inputs[2], inputs[4] = nbr, hits
    again = run_onnx(files["onnx"], inputs)
    assert all(np.array_equal(a, b) for a, b in zip(base, again))


def test_onnx_runs_without_torch_or_egcbf(exported, tmp_path):
    ctrl, files = exported
    inputs = next(_observations(ctrl, 5, 10, 1.5, 1))
    np.savez(tmp_path / "in.npz", **{n: a.numpy() for n, a in zip(INPUT_NAMES, inputs)})
    script = f"""
import sys, numpy as np, onnxruntime
feeds = dict(np.load({str(tmp_path / "in.npz")!r}))
s = onnxruntime.InferenceSession({str(files["onnx"])!r}, providers=["CPUExecutionProvider"])
out = s.run({list(OUTPUT_NAMES)!r}, feeds)
assert not any(m == "torch" or m.startswith(("torch.", "egcbf", "groupcanon")) for m in sys.modules), "imported"
np.savez({str(tmp_path / "out.npz")!r}, u=out[0], command=out[1])
"""
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120)
    got = np.load(tmp_path / "out.npz")
    with torch.no_grad():
        want = ctrl.module(*inputs)
    for name, w in zip(OUTPUT_NAMES, want):
        assert np.abs(got[name] - w.numpy()).max() <= TOL, name


def test_the_files_carry_their_layout(exported):
    import onnx

    files = exported[1]
    sidecar = json.loads(files["onnx"].with_name("agent.onnx.json").read_text())
    assert sidecar["max_neighbours"] == MAX_NEIGHBOURS and sidecar["max_hits"] == MAX_HITS
    assert sidecar["inputs"]["neighbours"]["shape"] == [MAX_NEIGHBOURS, 18] and len(sidecar["checkpoint_sha256"]) == 64
    meta = {p.key: p.value for p in onnx.load(str(files["onnx"])).metadata_props}
    assert json.loads(meta["egcbf"]) == sidecar
    extra = {"egcbf.json": ""}
    torch.jit.load(str(files["torchscript"]), _extra_files=extra)
    assert json.loads(extra["egcbf.json"]) == json.loads(
        files["torchscript"].with_name("agent.torchscript.json").read_text()
    )
    session = onnxruntime.InferenceSession(str(files["onnx"]), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == list(INPUT_NAMES)
    assert [o.name for o in session.get_outputs()] == list(OUTPUT_NAMES)


def test_the_command(tmp_path):
    out = tmp_path / "a.pt"
    args = ["export", "--checkpoint", str(ROOT / "egcbf+"), "--format", "torchscript", "--out", str(out)]
    res = CliRunner().invoke(app, [*args, "--max-neighbours", "3", "--max-hits", "2"])
    assert res.exit_code == 0, res.output
    assert json.loads(Path(str(out) + ".json").read_text())["max_neighbours"] == 3
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2 and "--overwrite" in res.output
    res = CliRunner().invoke(app, [*args, "--overwrite", "--max-neighbours", "0"])
    assert res.exit_code == 2 and "--max-neighbours must be >= 1" in res.output
    res = CliRunner().invoke(app, [*args[:-1], str(tmp_path), "--overwrite"])
    assert res.exit_code == 2 and "is a directory" in res.output
    res = CliRunner().invoke(
        app, ["export", "--checkpoint", str(tmp_path), "--format", "onnx", "--out", str(tmp_path / "b")]
    )
    assert res.exit_code == 2 and "--checkpoint" in res.output


def test_every_robot_exports_at_the_default_limits(tmp_path):
    """The example inputs a file is checked on fit every robot at the default 64 neighbour rows (no sampling
    separation), and a point-mass policy (frame averaging) traces to the same outputs."""
    from egcbf.algo import GraphCBFLearner
    from egcbf.algo.config import TrainConfig
    from egcbf.env import EnvConfig

    for robot in ("double_integrator", "dubins_car"):
        learner = GraphCBFLearner(TrainConfig.preset("egcbf+", "cpu", robot=robot))
        env = EnvConfig.for_robot(robot, num_agents=1)
        ctrl = AgentController(learner.policy, learner.config.model, env)
        path = export_controller(ctrl, "torchscript", tmp_path / f"{robot}.pt")
        assert json.loads(Path(str(path) + ".json").read_text())["max_neighbours"] == 64
