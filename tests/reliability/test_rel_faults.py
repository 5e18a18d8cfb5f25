"""``--faults`` means what it says on every robot: the default field conditions leave out what a robot cannot take
(and say so, and record it), a fault the spec names itself that the robot cannot take is refused up front, a JSON
file takes the short names the error lists, and a run that fails before any result leaves nothing behind."""

import json
from pathlib import Path

from rel_helpers import assert_usage_error

DI = Path(__file__).resolve().parents[2] / "checkpoints" / "double_integrator" / "egcbf+"
RUN = ["--num-agents", "8", "--area", "2", "--episodes", "1", "--max-steps", "3", "--no-progress"]


def test_default_faults_on_a_robot_without_thrust_leave_thrust_out_and_say_so(cli, tmp_path):
    res = cli("eval", "--checkpoint", DI, "--faults", "default", *RUN, "--out", tmp_path / "ev")
    assert res.exit_code == 0, res.output
    assert "left out thrust_gain" in res.output and "rounds to no non-cooperative agent" in res.output
    run = json.loads((tmp_path / "ev" / "run.json").read_text())
    assert run["faults_left_out"] == ["thrust_gain"] and run["faults"]["thrust_gain"] == 0
    assert run["noncoop_agents"] == {"8": 0} and run["faults"]["msg_loss"] == 0.1


def test_a_fault_named_by_the_spec_that_the_robot_cannot_take_is_refused_up_front(cli, tmp_path):
    res = cli("eval", "--checkpoint", DI, "--faults", "default,thrust_gain=0.1", *RUN, "--out", tmp_path / "ev")
    assert_usage_error(res, "thrust_gain needs the robot's 'thrust' channels", "double_integrator")
    assert not (tmp_path / "ev").exists()
    fixed = cli("eval", "--checkpoint", DI, "--faults", "default", *RUN, "--out", tmp_path / "ev")
    assert fixed.exit_code == 0, fixed.output  # nothing left behind blocks the corrected rerun


def test_a_fault_file_takes_the_short_names(cli, tmp_path):
    spec = tmp_path / "faults.json"
    spec.write_text(json.dumps({"loss": 0.2, "pos": 0.01}))
    res = cli("eval", "--checkpoint", DI, "--faults", spec, *RUN, "--out", tmp_path / "ev")
    assert res.exit_code == 0, res.output
    faults = json.loads((tmp_path / "ev" / "run.json").read_text())["faults"]
    assert faults["msg_loss"] == 0.2 and faults["pos_noise"] == 0.01
    spec.write_text(json.dumps({"loss": 0.2, "msg_loss": 0.3}))
    assert_usage_error(cli("eval", "--checkpoint", DI, "--faults", spec, *RUN, "--out", tmp_path / "x"), "twice")


def test_a_run_that_fails_before_any_result_leaves_nothing(cli, tmp_path, monkeypatch):
    import egcbf.evaluate.episodes

    def broken(*args, **kwargs):
        raise RuntimeError("simulated failure in the first swarm size")

    monkeypatch.setattr(egcbf.evaluate.episodes, "evaluate", broken)
    res = cli("eval", *RUN, "--out", tmp_path / "ev")
    assert res.exit_code != 0 and isinstance(res.exception, RuntimeError)
    assert not (tmp_path / "ev" / "run.json").exists()
