"""egcbf.io.allocator: the CLI's malloc setting applies on glibc, can be turned off, and says which (subprocesses:
the setting is process-wide, so it is never applied to the test process itself)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

CODE = "import json; from egcbf.io.allocator import keep_freed_memory; print(json.dumps(keep_freed_memory()))"


def _run(**env: str) -> tuple[bool, str]:
    out = subprocess.run([sys.executable, "-c", CODE], env={**os.environ, **env}, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    applied, reason = json.loads(out.stdout.strip().splitlines()[-1])
    return applied, reason


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_applies_on_glibc():
    applied, reason = _run()
    assert applied and "keeps freed memory" in reason


def test_environment_variable_turns_it_off():
    applied, reason = _run(EGCBF_KEEP_FREED_MEMORY="0")
    assert not applied and "EGCBF_KEEP_FREED_MEMORY=0" in reason


def test_cli_records_the_setting(tmp_path):
    """`egcbf eval` (the console entry point) applies it and writes it into run.json."""
    out = tmp_path / "eval"
    cmd = [sys.executable, "-c", "from egcbf.cli import main; main()", "eval", "--controller", "nominal",
           "--num-agents", "4", "--area", "1.5", "--episodes", "1", "--max-steps", "3", "--out", str(out),
           "--no-render", "--no-progress", "--threads", "1"]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    meta = json.loads((out / "run.json").read_text())
    glibc = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"
    assert ("keeps freed memory" in meta["allocator"]) == glibc
