"""benchmarks/env_scaling.py keeps working (tiny sizes) and rewrites only its own section of the report."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _module():
    spec = importlib.util.spec_from_file_location("env_scaling", ROOT / "benchmarks" / "env_scaling.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_quick_run_and_section_update(tmp_path, capsys):
    mod = _module()
    out = tmp_path / "benchmarks.md"
    out.write_text("# Benchmarks\n\n## Other\n\nkeep me\n")
    assert mod.main(["--sizes", "16", "32", "--repeats", "1", "--area", "2", "--out", str(out)]) == 0
    text = out.read_text()
    assert "keep me" in text and text.count(mod.BEGIN) == 1 and text.count(mod.END) == 1
    assert "| 32 | 2.00 |" in text and "fixed density" in capsys.readouterr().out
    mod.write_section(out, "replaced")  # a second write replaces the section in place
    text = out.read_text()
    assert "keep me" in text and f"{mod.BEGIN}\nreplaced\n{mod.END}" in text and "| 32 |" not in text
