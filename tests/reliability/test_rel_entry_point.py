"""The installed ``egcbf`` command: its entry point is ``egcbf.cli:main`` (allocator setting, one-line errors)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from egcbf import cli

ROOT = Path(__file__).resolve().parents[2]


def test_the_console_script_runs_main():
    text = (ROOT / "pyproject.toml").read_text()
    scripts = text.split("[project.scripts]", 1)[1].split("\n[", 1)[0]
    assert 'egcbf = "egcbf.cli:main"' in scripts  # `app` alone would skip the allocator setting and the error lines


@pytest.mark.parametrize(
    "args, phrases",
    [
        (["eval", "--episodes", "x"], ["--episodes", "integer", "egcbf eval --help"]),
        (["eval", "--area", "wide"], ["--area"]),
        (["demo", "--num-agents", "1.5"], ["--num-agents"]),
        (["evl"], ["No such command", "eval"]),
        (["eval", "--no-such-flag"], ["--no-such-flag"]),
        (["train", "--steps"], ["--steps", "requires an argument"]),
    ],
)
def test_bad_flag_types_are_one_error_line(args, phrases, monkeypatch, capsys):
    monkeypatch.delenv("EGCBF_DEBUG", raising=False)
    with pytest.raises(SystemExit) as exit_:
        cli.main(args)
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("Error: ") and len(err.splitlines()) == 1, err
    assert "Traceback" not in err and "╭" not in err  # no boxed panel
    for phrase in phrases:
        assert phrase in err


def test_debug_shows_the_exception(monkeypatch):
    monkeypatch.setenv("EGCBF_DEBUG", "1")
    with pytest.raises(Exception) as raised:
        cli.main(["eval", "--episodes", "x"])
    assert "--episodes" in raised.value.format_message()


def test_no_arguments_prints_help_and_succeeds(capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main([])
    assert exit_.value.code == 0 and "Usage" in capsys.readouterr().out


def test_the_command_records_the_allocator_setting(tmp_path):
    out = tmp_path / "ev"
    args = ["eval", "--num-agents", "2", "--area", "1.5", "--episodes", "1", "--max-steps", "2", "--no-progress"]
    code = "import sys; from egcbf.cli import main; main(sys.argv[1:])"
    res = subprocess.run([sys.executable, "-c", code, *args, "--out", str(out), "--threads", "1"],
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr
    allocator = json.loads((out / "run.json").read_text())["allocator"]
    assert "did not run" not in allocator
