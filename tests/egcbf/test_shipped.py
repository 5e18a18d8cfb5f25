"""The shipped checkpoints (checkpoints/README.md): each loads safely, is the method its directory names, matches
the recipe it is documented as, and drives a small swarm."""

import json
from pathlib import Path

import pytest
import shipped_reference
import torch

from egcbf.algo.config import TrainConfig
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.train.checkpoint import load_controller

ROOT = Path(__file__).resolve().parents[2] / "checkpoints"
#: the graph-policy checkpoints (a MARL baseline's directory, with marl.json, is tested below)
SHIPPED = sorted(p.parent for p in ROOT.glob("**/model.safetensors") if not (p.parent / "marl.json").exists())
MARL = sorted(p.parent for p in ROOT.glob("**/marl.json"))


@pytest.mark.parametrize("path", MARL, ids=[str(p.relative_to(ROOT)) for p in MARL])
def test_shipped_marl_checkpoint_is_its_documented_run_and_acts(path):
    """The shipped MARL baseline is the run checkpoints/README.md documents (the default configuration of its
    trainer, its training seed, the budget it trained for) and drives a small swarm as a controller."""
    from egcbf.control.resolve import resolve
    from egcbf.marl.checkpoint import MarlTrainConfig, read_marl_config

    config, progress = read_marl_config(path)
    assert config.algo == path.name
    assert config == MarlTrainConfig(seed=config.seed, max_minutes=config.max_minutes)
    assert progress["wall_s"] <= 60 * config.max_minutes + 120 and (path / "metrics.csv").exists()
    built = resolve("policy", path)
    env_cfg = EnvConfig.for_robot(config.robot, num_agents=4, num_envs=1, area_size=1.5, num_obstacles=1)
    u, _ = built.controller(SwarmEnv(env_cfg).reset(0), env_cfg)
    assert u.shape == (1, 4, env_cfg.make_robot().control_dim) and torch.isfinite(u).all()


def test_the_command_interface_methods_are_at_the_top_level():
    for algo in ("egcbf+", "gcbf+"):
        cfg = TrainConfig.from_json(ROOT / algo / "config.json")
        assert cfg.model.interface == "accel" and cfg.model.policy_head == "edge_sum", algo


@pytest.mark.parametrize("path", SHIPPED, ids=[str(p.relative_to(ROOT)) for p in SHIPPED])
def test_shipped_checkpoint_loads_and_acts(path):
    cfg = TrainConfig.from_json(path / "config.json")
    name, _, seed = path.name.rpartition("-s")
    seeded = bool(name) and seed.isdigit()  # <algo>-s<k>: training seed k (seeds/, paper-target/)
    assert cfg.algo == (name if seeded else path.name)
    if seeded:
        assert cfg.seed == int(seed)
    if cfg.init_from is not None:  # a fine-tuned policy names the shipped weights it started from
        start = Path(__file__).resolve().parents[2] / cfg.init_from
        assert json.loads((start / "state.json").read_text())["weights_sha256"] == cfg.init_sha256
    state = json.loads((path / "state.json").read_text())
    assert state["step"] >= 0
    if "weight_average" not in state:  # a trained checkpoint carries its run's validations
        assert (path / "metrics.csv").exists()
    ctrl, _ = load_controller(path)
    env_cfg = EnvConfig.for_robot(cfg.robot, num_agents=4, num_envs=1, area_size=1.5, num_obstacles=1)
    state = SwarmEnv(env_cfg).reset(0)
    u, info = ctrl(state, env_cfg)
    k = env_cfg.make_robot().control_dim
    assert u.shape == (1, 4, k) and torch.isfinite(u).all() and info["num_failed"] == 0


@pytest.mark.parametrize("method", shipped_reference.METHODS)
def test_shipped_policy_outputs_are_unchanged(method):
    """Regression: the shipped networks compute what they computed when recorded (tests/egcbf/shipped_reference.py,
    recorded when each checkpoint was added). float64, 1e-9: only rounding may differ."""
    ref = shipped_reference
    data = json.loads(ref.DATA.read_text())[method]
    if data["sha256"] != ref.checkpoint_hash(method):
        pytest.fail(f"checkpoints/{method} was replaced: regenerate with `python tests/egcbf/shipped_reference.py`")
    now = ref.outputs(method)
    for key in ("pi", "h", "u"):
        got, expected = torch.tensor(now[key], dtype=torch.float64), torch.tensor(data[key], dtype=torch.float64)
        assert got.shape == expected.shape, key
        assert torch.allclose(got, expected, rtol=0.0, atol=1e-9), (key, (got - expected).abs().max().item())


@pytest.mark.parametrize("state", sorted(ROOT.glob("**/state.json")), ids=lambda p: str(p.parent.relative_to(ROOT)))
def test_shipped_checkpoints_carry_their_identity(state):
    """Every shipped checkpoint says what it is (format, method, group, interface, weights hash) and matches it."""
    from egcbf.train.checkpoint import FORMAT_VERSION, check_identity, identity, read_config

    meta = json.loads(state.read_text())
    cfg = read_config(state.parent)
    assert {k: meta[k] for k in identity(cfg)} == identity(cfg) and meta["format_version"] == FORMAT_VERSION
    assert len(meta["weights_sha256"]) == 64
    check_identity(state.parent, cfg)


AVERAGED = [p for p in SHIPPED if "weight_average" in json.loads((p / "state.json").read_text())]


@pytest.mark.parametrize("path", AVERAGED, ids=[str(p.relative_to(ROOT)) for p in AVERAGED])
def test_averaged_checkpoints_are_their_recorded_average(path, tmp_path):
    """A weight-averaged checkpoint (``egcbf average``) names its two inputs, which are still shipped with the
    weights they had, and rebuilding it from them gives the same tensors exactly."""
    from egcbf.train.averaging import average_checkpoints
    from egcbf.train.checkpoint import read_tensors, sha256

    rec = json.loads((path / "state.json").read_text())["weight_average"]
    repo = ROOT.parent
    for k in ("a", "b"):
        assert sha256(repo / rec[k] / "model.safetensors") == rec[f"{k}_sha256"], k
    rebuilt = read_tensors(
        average_checkpoints(repo / rec["a"], repo / rec["b"], rec["lam"], tmp_path / "x") / "model.safetensors"
    )
    shipped = read_tensors(path / "model.safetensors")
    assert rebuilt.keys() == shipped.keys() and all(torch.equal(rebuilt[k], shipped[k]) for k in shipped)
