"""The command line's fixed choices are enums: they agree with the library's registries, `--help` lists them, a value
outside them is one `Error:` line naming the flag and the choices, and the commands pass plain strings on."""

import json

import pytest
from typer.testing import CliRunner

from egcbf import cli
from egcbf.algo.config import LEARNED_METHODS, PRESETS
from egcbf.cli.choices import (
    Backend,
    Controller,
    DemoMethod,
    Dtype,
    ExportFormat,
    LearnedMethod,
    Preset,
    RobotName,
    SafetyFilter,
    SceneName,
    choice_error,
)
from egcbf.cli.eval import DTYPES
from egcbf.control.controllers import CONTROLLERS
from egcbf.control.filters import FILTERS
from egcbf.deploy.export import FORMATS
from egcbf.env.scenes import SCENES
from egcbf.reproduce.plan import BACKENDS
from egcbf.robots import BUILTIN_ROBOTS, ROBOTS

OPTIONS = [  # (command, flag, enum)
    ("eval", "--controller", Controller),
    ("eval", "--dtype", Dtype),
    ("eval", "--filter", SafetyFilter),
    ("eval", "--scene", SceneName),
    ("demo", "--method", DemoMethod),
    ("train", "--algo", LearnedMethod),
    ("train", "--preset", Preset),
    ("reproduce", "--backend", Backend),
    ("export", "--format", ExportFormat),
]


def _values(enum) -> list[str]:
    return [m.value for m in enum]


def test_the_choices_are_the_library_registries():
    assert _values(Controller) == list(CONTROLLERS)
    assert _values(LearnedMethod) == list(LEARNED_METHODS)
    assert _values(DemoMethod) == [*LEARNED_METHODS, *CONTROLLERS]
    assert _values(Preset) == list(PRESETS)
    assert _values(Dtype) == list(DTYPES)
    assert _values(Backend) == list(BACKENDS)
    assert (
        _values(RobotName)
        == [r for r in ROBOTS if r in BUILTIN_ROBOTS]
        == sorted(BUILTIN_ROBOTS, key=list(ROBOTS).index)
    )
    assert _values(SafetyFilter) == list(FILTERS)
    assert _values(SceneName) == list(SCENES)
    assert _values(ExportFormat) == list(FORMATS)
    enums = (Controller, LearnedMethod, DemoMethod, Preset, Dtype, Backend, RobotName, SafetyFilter, SceneName)
    for enum in (*enums, ExportFormat):
        assert all(isinstance(m, str) and json.dumps(m) == json.dumps(m.value) for m in enum)


@pytest.mark.parametrize("command, flag, enum", OPTIONS)
def test_help_lists_the_choices(command, flag, enum):
    res = CliRunner().invoke(cli.app, [command, "--help"], env={"COLUMNS": "400"})
    assert res.exit_code == 0, res.output
    line = next(line for line in res.output.splitlines() if f" {flag} " in line)
    assert "|".join(_values(enum)) in line, line


@pytest.mark.parametrize("command, flag, enum", OPTIONS)
def test_a_value_outside_the_choices_is_one_error_line(command, flag, enum, monkeypatch, capsys):
    monkeypatch.delenv("EGCBF_DEBUG", raising=False)
    with pytest.raises(SystemExit) as exit_:
        cli.main([command, flag, "bogus"])
    err = capsys.readouterr().err.strip()
    res = CliRunner().invoke(cli.app, [command, flag, "bogus"], env={"COLUMNS": "400"})
    for code, text in ((exit_.value.code, err), (res.exit_code, res.output.strip())):
        assert code == 2 and text.startswith("Error: ") and len(text.splitlines()) == 1, text
        assert f"{flag}: unknown" in text and "'bogus'" in text and "╭" not in text
        assert "choose one of " + ", ".join(_values(enum)) in text, text
    assert f"see `egcbf {command} --help`" in err


def test_choice_error_reads_the_messages_of_typer_and_click():
    assert choice_error("--algo", "algo", "Value error, 'x' is not one of 'gcbf', 'gcbf+'.") == (
        "--algo: unknown algo 'x'; choose one of gcbf, gcbf+"
    )
    assert choice_error("--algo", "algo", "'x' is not one of 'gcbf', 'gcbf+'.").endswith("gcbf, gcbf+")
    assert choice_error("--episodes", "episodes", "'x' is not a valid integer.") is None


def test_the_commands_pass_plain_strings_on(monkeypatch, tmp_path):
    """Library code and the configs saved beside checkpoints get strings, never enum members."""
    import egcbf.cli.demo
    import egcbf.cli.eval
    import egcbf.reproduce
    import egcbf.train.loop

    seen = {}
    monkeypatch.setattr(egcbf.cli.eval, "run_eval", lambda **kw: seen.update(eval=kw))
    monkeypatch.setattr(egcbf.train.loop, "train", lambda config, out, **kw: seen.update(train=config))
    monkeypatch.setattr(egcbf.cli.demo, "run_demo", lambda sources, **kw: seen.update(demo=sources))

    def sweep_config(**kw):
        seen["reproduce"] = kw
        raise ValueError("stop here")

    monkeypatch.setattr(egcbf.reproduce, "SweepConfig", sweep_config)
    run = CliRunner().invoke
    assert run(cli.app, ["eval", "--controller", "ccbf", "--dtype", "float64", "--threads", "1"]).exit_code == 0
    args = ["train", "--algo", "gcbf+", "--preset", "tiny", "--out", str(tmp_path / "run"), "--no-progress"]
    assert run(cli.app, args).exit_code == 0
    args = ["demo", "--method", "dcbf", "--compare", "none", "--out", str(tmp_path / "demo"), "--threads", "1"]
    assert run(cli.app, args).exit_code == 0
    assert run(cli.app, ["reproduce", "--backend", "ray", "--methods", "nominal"]).exit_code == 2
    assert type(seen["eval"]["controller"]) is str and type(seen["eval"]["dtype"]) is str
    config = seen["train"]
    assert (type(config.algo), config.algo, type(config.group)) == (str, "gcbf+", str)
    assert list(seen["demo"]) == ["dcbf"] and all(type(k) is str for k in seen["demo"])
    assert type(seen["reproduce"]["backend"]) is str and seen["reproduce"]["backend"] == "ray"


def test_a_robot_registered_by_the_user_is_accepted_by_eval_robot(tmp_path):
    """``--robot`` takes the registry as it stands when the command runs: examples/new_robot.py's robot, once
    registered, is evaluated; an unknown name is one error line listing the registered robots, the user's too."""
    import importlib.util
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "examples" / "new_robot.py"
    spec = importlib.util.spec_from_file_location("new_robot_example", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["new_robot_example"] = module
    spec.loader.exec_module(module)  # registers DiffDrive as "diffdrive"
    name = module.DiffDrive.name
    try:
        assert name in ROBOTS and name not in _values(RobotName)
        res = CliRunner().invoke(cli.app, ["eval", "--controller", "nominal", "--robot", name, "--num-agents", "4",
                                           "--area", "2", "--episodes", "1", "--max-steps", "5", "--out",
                                           str(tmp_path / "o"), "--no-progress"])  # fmt: skip
        assert res.exit_code == 0, res.output
        assert json.loads((tmp_path / "o" / "run.json").read_text())["robot"] == name
        res = CliRunner().invoke(cli.app, ["eval", "--controller", "nominal", "--robot", "bogus", "--out",
                                           str(tmp_path / "p"), "--no-progress"])  # fmt: skip
        assert res.exit_code == 2 and "--robot: unknown robot 'bogus'" in res.output and name in res.output, res.output
        assert not (tmp_path / "p").exists()
    finally:  # the registry as the other tests expect it
        del ROBOTS[name]
        sys.modules.pop("new_robot_example", None)
