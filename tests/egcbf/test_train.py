"""Training runs: configs, the four methods end to end, checkpoints, bit-for-bit resume, eval from a checkpoint."""

import csv
import json

import pytest
import torch
from typer.testing import CliRunner

from egcbf.algo import GraphCBFLearner
from egcbf.algo.config import LEARNED_METHODS, TrainConfig
from egcbf.cli import app
from egcbf.env import SwarmEnv
from egcbf.train.checkpoint import CheckpointError, find_checkpoint, load_controller, load_learner
from egcbf.train.loop import train


def _quiet(cfg, out, **kw):
    return train(cfg, out, progress=False, log=lambda line: None, **kw)


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_config_presets_and_json_roundtrip(tmp_path):
    paper = TrainConfig.preset("egcbf+", "paper")
    # GCBF+: 16 envs x 256 steps per update, 8 epochs x 48 minibatches of 256 graphs
    graphs = paper.rollout_envs * paper.rollout_steps * 2 + paper.unsafe_samples
    assert (paper.rollout_envs, paper.rollout_steps, paper.epochs, graphs // paper.batch_size) == (16, 256, 8, 48)
    assert (paper.lr_cbf, paper.lr_policy, paper.gamma, paper.eta_d, paper.alpha) == (1e-4, 1e-5, 0.02, 0.2, 1.0)
    for algo, (group, reference) in LEARNED_METHODS.items():
        cfg = TrainConfig.preset(algo, "cpu", seed=3, model={"hidden": 32})
        group = {"equivariant": "se2xr"}.get(group, group)  # the quadrotor's group
        assert (cfg.group, cfg.reference, cfg.seed, cfg.model.hidden) == (group, reference, 3, 32)
        cfg.to_json(tmp_path / "c.json")
        assert TrainConfig.from_json(tmp_path / "c.json") == cfg
    cpu = TrainConfig.preset("gcbf", "cpu")
    env = cpu.env_config()
    assert (env.num_agents, env.area_size, env.num_obstacles) == (32, 2.0, 4)
    # the density recipe: the rollout of update k uses area_sizes[k % 3]; up to 7.8 agents per m^3
    assert [cpu.area_of_update(k) for k in range(4)] == [1.6, 2.0, 2.5, 1.6]
    assert max(cpu.num_agents / a**3 for a in cpu.area_sizes) > 7.5
    assert cpu.model.interface == "accel" and TrainConfig.preset("gcbf", "cpu-torque").model.interface == "torque"
    with pytest.raises(ValueError, match="area_sizes"):
        TrainConfig.preset("gcbf", "tiny", area_sizes=[])
    with pytest.raises(ValueError, match="command_model"):
        TrainConfig.preset("gcbf", "tiny", command_model="exact")
    with pytest.raises(ValueError, match="group"):
        TrainConfig(algo="egcbf", reference="nominal")  # the default model group is se2xr: fine ...
        TrainConfig(algo="gcbf", reference="nominal")  # ... but gcbf needs the trivial group
    with pytest.raises(ValueError, match="unknown TrainConfig fields"):
        TrainConfig.from_dict({"algo": "gcbf", "bogus": 1})
    with pytest.raises(ValueError, match="batch_size"):
        TrainConfig.preset("gcbf", "tiny", batch_size=0)


@pytest.mark.parametrize(
    "algo, interface, model",
    [(a, "accel", "ideal") for a in sorted(LEARNED_METHODS)]
    + [("egcbf+", "accel", "closed_loop"), ("gcbf+", "torque", "")],
)
def test_each_method_trains_end_to_end(tmp_path, algo, interface, model):
    changes = {"command_model": model} if model else {}
    head = {} if interface == "accel" else {"policy_head": "mlp"}  # the edge-sum head needs a vector command
    cfg = TrainConfig.preset(algo, "tiny", steps=2, model={"interface": interface, **head}, **changes)
    learner = _quiet(cfg, tmp_path)
    assert learner.step == 2
    ckpt = find_checkpoint(tmp_path)
    assert ckpt.name == "step_000002"
    for name in ("config.json", "model.safetensors", "training_state.pt", "buffers.safetensors", "state.json"):
        assert (ckpt / name).exists(), name
    metrics = _rows(tmp_path / "metrics.csv")
    assert [int(r["step"]) for r in metrics] == [0, 2]
    for r in metrics:
        assert 0 <= float(r["safe_rate"]) <= 1 and 0 <= float(r["reach_rate"]) <= 1 and float(r["wall_s"]) >= 0
    tags = {r["tag"] for r in _rows(tmp_path / "scalars.csv")}
    assert {"loss/total", "loss/hdot", "data/safe", "data/unsafe", "data/unlabelled"} <= tags
    assert ("qp/num_slack" in tags) == (cfg.reference == "qp")


def test_resume_continues_bit_for_bit(tmp_path, monkeypatch):
    cfg = TrainConfig.preset("egcbf+", "tiny", steps=4, checkpoint_interval=2, eval_interval=2)
    full = _quiet(cfg, tmp_path / "full")
    update = GraphCBFLearner.update

    def crash_in_update_4(self):
        if self.step == 3:
            raise KeyboardInterrupt  # interrupted after update 3; the newest checkpoint is update 2
        return update(self)

    monkeypatch.setattr(GraphCBFLearner, "update", crash_in_update_4)
    with pytest.raises(KeyboardInterrupt):
        _quiet(cfg, tmp_path / "part")
    monkeypatch.undo()
    assert [p.name for p in (tmp_path / "part" / "checkpoints").iterdir()] == ["step_000002"]
    (tmp_path / "part" / "checkpoints" / "step_000004.tmp").mkdir()  # a half-written checkpoint is ignored
    resumed = _quiet(cfg, tmp_path / "part", resume=True)
    assert resumed.step == full.step == 4
    wf, wr = full.weights(), resumed.weights()
    assert wf.keys() == wr.keys() and all(torch.equal(wf[k], wr[k]) for k in wf)
    for a, b in ((full.opt_cbf, resumed.opt_cbf), (full.opt_policy, resumed.opt_policy)):
        sa, sb = a.state_dict()["state"], b.state_dict()["state"]
        assert all(torch.equal(sa[i]["exp_avg"], sb[i]["exp_avg"]) and sa[i]["step"] == sb[i]["step"] for i in sa)
    assert torch.equal(full.generator.get_state(), resumed.generator.get_state())
    assert torch.equal(full.buffer.data.x, resumed.buffer.data.x) and len(full.unsafe_buffer) == len(
        resumed.unsafe_buffer
    )

    def untimed(run):
        rows = _rows(tmp_path / run / "metrics.csv")
        return [{k: v for k, v in r.items() if k not in ("wall_s", "cpu_s")} for r in rows]

    assert untimed("full") == untimed("part")
    steps = [int(r["step"]) for r in _rows(tmp_path / "part" / "scalars.csv")]
    assert steps == sorted(steps) and max(steps) == 4  # rows after the checkpoint were replaced, not duplicated
    with pytest.raises(FileExistsError):
        _quiet(cfg, tmp_path / "full")


def test_checkpoint_roundtrip_and_controller(tmp_path):
    cfg = TrainConfig.preset("gcbf+", "tiny", steps=2)
    learner = _quiet(cfg, tmp_path)
    loaded = load_learner(tmp_path)
    assert loaded.step == 2 and loaded.config == cfg
    assert all(torch.equal(v, loaded.weights()[k]) for k, v in learner.weights().items())
    ctrl, cfg2 = load_controller(find_checkpoint(tmp_path))
    assert cfg2 == cfg
    env = SwarmEnv(cfg.env_config(num_envs=2))
    state = env.reset(7)
    u1, info1 = learner.controller()(state, env.config)
    u2, info2 = ctrl(state, env.config)
    assert torch.equal(u1, u2) and torch.equal(info1["u_ref"], info2["u_ref"])
    # weights only: the controller needs nothing but config.json and model.safetensors
    only = tmp_path / "only"
    only.mkdir()
    for name in ("config.json", "model.safetensors"):
        (only / name).write_bytes((find_checkpoint(tmp_path) / name).read_bytes())
    u3, _ = load_controller(only)[0](state, env.config)
    assert torch.equal(u1, u3)


def test_cli_train_resume_and_eval_checkpoint(tmp_path):
    run = tmp_path / "run"
    (tmp_path / "cfg.json").write_text(json.dumps({"preset": "tiny", "steps": 2, "model": {"hidden": 8}}))
    r = CliRunner().invoke(app, ["train", "--algo", "egcbf", "--config", str(tmp_path / "cfg.json"), "--out",
                                 str(run), "--seed", "5", "--no-progress"])  # fmt: skip
    assert r.exit_code == 0, r.output
    saved = TrainConfig.from_json(run / "config.json")
    assert (saved.algo, saved.steps, saved.seed, saved.model.hidden, saved.model.group) == ("egcbf", 2, 5, 8, "se2xr")
    r = CliRunner().invoke(app, ["train", "--out", str(run), "--resume", "--steps", "3", "--no-progress"])
    assert r.exit_code == 0, r.output
    assert find_checkpoint(run).name == "step_000003"
    r = CliRunner().invoke(app, ["train", "--algo", "egcbf", "--preset", "tiny", "--out", str(run), "--no-progress"])
    assert r.exit_code != 0 and "resume" in r.output
    r = CliRunner().invoke(app, ["train", "--algo", "sgd", "--out", str(tmp_path / "x")])
    assert r.exit_code != 0 and "algo" in r.output
    out = tmp_path / "ev"
    args = ["--num-agents", "2,4", "--area", "1.5", "--episodes", "2", "--max-steps", "10", "--no-progress"]
    r = CliRunner().invoke(app, ["eval", "--checkpoint", str(run), "--out", str(out), *args])
    assert r.exit_code == 0, r.output
    rows = json.loads((out / "metrics.json").read_text())
    assert [row["num_agents"] for row in rows] == [2, 4] and "Safe%" in r.output
    assert json.loads((out / "run.json").read_text())["controller"] == "egcbf"
    r = CliRunner().invoke(app, ["eval", "--checkpoint", str(tmp_path / "nothing"), "--out", str(out)])
    assert r.exit_code != 0 and "no checkpoint" in r.output


def test_best_policy_is_the_best_evaluated_one(tmp_path):
    cfg = TrainConfig.preset("egcbf", "tiny", steps=4, eval_interval=1)
    _quiet(cfg, tmp_path)
    rows = _rows(tmp_path / "metrics.csv")
    key = [(float(r["success_rate"]), float(r["safe_rate"]), int(r["step"])) for r in rows]
    best = json.loads((tmp_path / "best" / "state.json").read_text())
    assert best["step"] == max(key)[2]  # highest success, then safety, then the later update
    assert (best["metrics"]["success_rate"], best["metrics"]["safe_rate"]) == max(key)[:2]
    ctrl, cfg2 = load_controller(tmp_path / "best")
    assert ctrl.model_config == cfg.model  # a best/ directory is a checkpoint for evaluation
    assert cfg2 == cfg
    # a run directory: evaluation takes its best/, resuming its newest checkpoint
    assert find_checkpoint(tmp_path, prefer_best=True) == tmp_path / "best"
    assert find_checkpoint(tmp_path).name == "step_000004"
    out = tmp_path / "eval"
    r = CliRunner().invoke(app, ["eval", "--checkpoint", str(tmp_path), "--num-agents", "2", "--episodes", "1",
                                 "--max-steps", "3", "--out", str(out), "--no-progress"])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert "evaluating its best/" in r.output
    assert json.loads((out / "run.json").read_text())["checkpoint"].endswith("best")


def test_max_wall_minutes_stops_with_a_final_evaluation_and_checkpoint(tmp_path):
    cfg = TrainConfig.preset("gcbf", "tiny", steps=4, max_wall_minutes=1e-9)
    learner = _quiet(cfg, tmp_path)
    assert learner.step == 1  # the first update already ends past the budget
    assert find_checkpoint(tmp_path).name == "step_000001"
    assert [int(r["step"]) for r in _rows(tmp_path / "metrics.csv")] == [0, 1]
    assert TrainConfig.preset("egcbf+", "cpu").max_wall_minutes == 60.0
    with pytest.raises(ValueError, match="max_wall_minutes"):
        TrainConfig.preset("gcbf", "tiny", max_wall_minutes=0)


def test_max_cpu_minutes_counts_process_time_and_survives_resume(tmp_path):
    """The CPU-time budget stops a run like the wall-time one, is logged (``cpu_s``), is stored in each checkpoint
    and continues from it on resume; a log written before ``cpu_s`` existed resumes without losing its rows."""
    cfg = TrainConfig.preset("gcbf", "tiny", steps=6, max_cpu_minutes=1e-9)
    learner = _quiet(cfg, tmp_path / "a")
    assert learner.step == 1
    rows = _rows(tmp_path / "a" / "metrics.csv")
    assert [int(r["step"]) for r in rows] == [0, 1] and float(rows[1]["cpu_s"]) > 0
    state = json.loads((find_checkpoint(tmp_path / "a") / "state.json").read_text())
    assert state["cpu_s"] >= float(rows[1]["cpu_s"]) > 0
    # resume: the clock starts where the checkpoint left it (a budget of 1000 CPU-minutes already spent)
    with pytest.raises(ValueError, match="max_cpu_minutes"):
        TrainConfig.preset("gcbf", "tiny", max_cpu_minutes=-1.0)
    run = tmp_path / "b"
    _quiet(TrainConfig.preset("gcbf", "tiny", steps=2, max_cpu_minutes=1000.0), run)
    ckpt = find_checkpoint(run)
    state = json.loads((ckpt / "state.json").read_text())
    (ckpt / "state.json").write_text(json.dumps({**state, "cpu_s": 1000.0 * 60.0}))
    metrics = run / "metrics.csv"
    old = [line.rsplit(",", 1)[0] for line in metrics.read_text().splitlines()]  # a log without the cpu_s column
    metrics.write_text("\n".join(old) + "\n")
    resumed = _quiet(TrainConfig.preset("gcbf", "tiny", steps=2), run, resume=True, steps=6)
    assert resumed.step == 3  # one more update, then the (already spent) budget stops it
    assert [int(r["step"]) for r in _rows(metrics)] == [0, 2, 3]  # the old rows kept (tiny evaluates every 2)


def test_resume_takes_the_threads_it_is_given(tmp_path, monkeypatch):
    """``egcbf train --resume --threads N``: the resumed run uses N threads, not the saved config's."""
    run = tmp_path / "run"
    _quiet(TrainConfig.preset("gcbf", "tiny", steps=2), run)
    before = torch.get_num_threads()
    seen = []
    update = GraphCBFLearner.update

    def note_threads(self):
        seen.append(torch.get_num_threads())
        return update(self)

    monkeypatch.setattr(GraphCBFLearner, "update", note_threads)
    resumed = _quiet(None, run, resume=True, steps=3, num_threads=2)
    assert resumed.config.num_threads == 2 and seen == [2] and torch.get_num_threads() == before


def test_warm_start_from_a_checkpoint(tmp_path):
    """``init_from`` starts a fresh run (update 0, fresh optimizers) from another run's networks and records the
    weights' SHA-256; another method, other networks or a changed file are refused, naming what differs."""
    first = tmp_path / "first"
    _quiet(TrainConfig.preset("egcbf+", "tiny", steps=2), first)
    source = find_checkpoint(first, prefer_best=True)
    cfg = TrainConfig.preset("egcbf+", "tiny", steps=1, num_agents=4, init_from=str(first))
    learner = GraphCBFLearner(cfg)
    from egcbf.train.checkpoint import sha256, warm_start

    ckpt, digest = warm_start(learner, first)
    assert ckpt == source and digest == sha256(source / "model.safetensors")
    want = load_learner(source).weights()
    assert all(torch.equal(v, want[k]) for k, v in learner.weights().items())
    assert learner.step == 0 and not learner.opt_policy.state  # fresh optimizers
    second = tmp_path / "second"
    trained = _quiet(cfg, second)
    saved = TrainConfig.from_json(second / "config.json")
    assert saved.init_from == str(first) and saved.init_sha256 == digest and trained.step == 1
    # what the run started from is checked when the config says it
    with pytest.raises(CheckpointError, match="init_sha256"):
        _quiet(cfg.replace(init_sha256="0" * 64), tmp_path / "third")
    with pytest.raises(CheckpointError, match="hidden: 16 there, 8 here"):
        warm_start(GraphCBFLearner(cfg.replace(model={**cfg.model.__dict__, "hidden": 8})), first)
    with pytest.raises(CheckpointError, match="holds egcbf\\+ weights"):
        warm_start(GraphCBFLearner(TrainConfig.preset("gcbf+", "tiny")), first)
    with pytest.raises(ValueError, match="init_sha256"):
        cfg.replace(init_sha256="not a hash")
    # the CLI names the option
    base = ["train", "--algo", "egcbf+", "--preset", "tiny", "--steps", "1", "--no-progress", "--init-from"]
    r = CliRunner().invoke(app, [*base, str(tmp_path / "missing"), "--out", str(tmp_path / "cli")])
    assert r.exit_code == 2 and "--init-from" in r.output, r.output
    r = CliRunner().invoke(app, [*base, str(first), "--out", str(tmp_path / "cli2")])
    assert r.exit_code == 0, r.output
    assert TrainConfig.from_json(tmp_path / "cli2" / "config.json").init_sha256 == digest


def test_env_overrides_refuse_the_runs_own_sizes_and_lengths():
    for key in ("max_steps", "num_agents", "area_size"):
        with pytest.raises(ValueError, match=f"free of \\['{key}'\\]"):
            TrainConfig.preset("egcbf+", "tiny", env_overrides={key: 5})
