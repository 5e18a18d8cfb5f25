"""The two distributions of the repository: ``egcbf`` (pyproject.toml: egcbf and groupcanon, the CLI's
dependencies) and ``groupcanon`` alone (packaging/groupcanon/pyproject.toml: only what groupcanon imports).

The static checks run always; the wheel is built by the slow tests (with the hatchling of the environment, the
``dev`` extra, or else in pip's isolated build environment, which needs PyPI)."""

import ast
import importlib.util
import os
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest

try:
    import tomllib
except ImportError:  # Python 3.10
    tomllib = pytest.importorskip("tomli")

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "groupcanon"
PKG = ROOT / "packaging" / "groupcanon"
#: groupcanon's runtime requirements (distribution name -> import name)
RUNTIME = {"torch": "torch", "torch-geometric": "torch_geometric", "roma": "roma"}
#: imports allowed in one module only, from the extra that provides them
EXTRA_IMPORTS = {"testing/strategies.py": {"hypothesis"}, "compat/escnn.py": {"escnn", "numpy"}}
#: egcbf's own dependencies that a groupcanon user must not need (tqdm is one of torch-geometric's)
NOT_NEEDED = ("egcbf", "hypothesis", "proxsuite", "piqp", "qpsolvers", "typer", "matplotlib", "scipy", "safetensors")


def _pyproject(path: Path) -> dict:
    return tomllib.loads(path.read_text())["project"]


def _name(requirement: str) -> str:
    """The distribution name of a requirement string (``"torch>=2.3"`` -> ``"torch"``)."""
    for i, ch in enumerate(requirement):
        if not (ch.isalnum() or ch in "-_."):
            return requirement[:i].strip().lower()
    return requirement.strip().lower()


def _imports(path: Path) -> set[str]:
    """Top-level names of the absolute imports of a module (at any depth: lazy imports count)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


# ---------------------------------------------------------------------------------------------------- static
def test_groupcanon_declares_what_it_imports():
    project = _pyproject(PKG / "pyproject.toml")
    assert project["name"] == "groupcanon"
    assert sorted(_name(r) for r in project["dependencies"]) == sorted(RUNTIME)
    assert [_name(r) for r in project["optional-dependencies"]["testing"]] == ["hypothesis"]
    allowed = set(sys.stdlib_module_names) | {"groupcanon", *RUNTIME.values()}
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC).as_posix()
        extra = _imports(path) - allowed - EXTRA_IMPORTS.get(rel, set())
        assert not extra, f"src/groupcanon/{rel} imports {sorted(extra)}: declare it in {PKG / 'pyproject.toml'}"


def test_the_distributions_agree():
    """The same requirement strings in both, one version source, and the groupcanon build's own files in place."""
    egcbf, gc = _pyproject(ROOT / "pyproject.toml"), _pyproject(PKG / "pyproject.toml")
    assert set(gc["dependencies"]) <= set(egcbf["dependencies"])
    assert gc["optional-dependencies"]["escnn"] == egcbf["optional-dependencies"]["escnn"]
    assert gc["optional-dependencies"]["testing"] == egcbf["optional-dependencies"]["testing"]
    assert not {_name(r) for r in egcbf["dependencies"]} & {"hypothesis"}  # only groupcanon.testing needs it
    assert (PKG / "src").resolve() == (ROOT / "src").resolve()  # a symbolic link: one copy of the sources
    assert (PKG / "LICENSE").read_text() == (ROOT / "LICENSE").read_text()
    import egcbf
    import groupcanon

    assert egcbf.__version__ == groupcanon.__version__


BLOCKER = """
import runpy, sys
for name in sys.argv[1].split(","):  # as if not installed: `import` raises, importlib.util.find_spec says None
    sys.modules[name] = None
import groupcanon, groupcanon.compat.escnn, groupcanon.testing
try:
    groupcanon.testing.strategies
except ModuleNotFoundError as err:
    assert "groupcanon[testing]" in str(err), err
else:
    raise AssertionError("hypothesis was blocked")
sys.argv = [sys.argv[2], "--nodes", "60"]
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def test_groupcanon_runs_without_the_dependencies_of_egcbf():
    """``import groupcanon`` and the everyday example work with egcbf, hypothesis and the CLI's and QP solvers'
    dependencies unimportable (the strategies say how to install hypothesis)."""
    res = subprocess.run(
        [sys.executable, "-c", BLOCKER, ",".join(NOT_NEEDED), str(ROOT / "examples" / "wrap_pyg_layer.py")],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert res.returncode == 0 and "OK" in res.stdout, res.stdout + res.stderr


# ---------------------------------------------------------------------------------------------------- builds
def _pip_wheel(source: Path, out: Path) -> Path:
    isolation = [] if importlib.util.find_spec("hatchling") is None else ["--no-build-isolation"]
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", *isolation, "-w", str(out), str(source)]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env={**os.environ, "PIP_NO_INPUT": "1"})
    assert res.returncode == 0, res.stdout + res.stderr
    (wheel,) = out.glob("groupcanon-*.whl")
    return wheel


def _check_wheel(wheel: Path) -> None:
    import groupcanon

    version = groupcanon.__version__
    info = f"groupcanon-{version}.dist-info/"
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        meta = z.read(info + "METADATA").decode()
    outside = [n for n in names if not (n.startswith("groupcanon/") or n.startswith(info))]
    assert not outside, f"the wheel holds more than groupcanon: {outside}"
    sources = {"groupcanon/" + p.relative_to(SRC).as_posix() for p in SRC.rglob("*.py")}
    assert {n for n in names if n.startswith("groupcanon/")} == sources  # every module, no bytecode
    fields = [line.split(": ", 1) for line in meta.splitlines() if ": " in line]
    assert ["Name", "groupcanon"] in fields and ["Version", version] in fields
    requires = [v for k, v in fields if k == "Requires-Dist"]
    plain = sorted(_name(r) for r in requires if ";" not in r)
    assert plain == sorted(RUNTIME), requires
    testing = [_name(r) for r in requires if r.replace('"', "'").endswith("extra == 'testing'")]
    assert testing == ["hypothesis"], requires
    assert not any(_name(r) in NOT_NEEDED for r in requires if ";" not in r)


@pytest.mark.slow
def test_groupcanon_wheel_holds_groupcanon_and_its_requirements_only(tmp_path):
    _check_wheel(_pip_wheel(PKG, tmp_path))


@pytest.mark.slow
def test_groupcanon_sdist_builds_the_same_wheel(tmp_path):
    """The sdist is self-contained (the symbolic links are resolved into it): a wheel builds from it alone."""
    pytest.importorskip("hatchling")
    code = "import sys; from hatchling.build import build_sdist; print(build_sdist(sys.argv[1]))"
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, cwd=PKG)
    assert res.returncode == 0, res.stdout + res.stderr
    sdist = tmp_path / res.stdout.strip().splitlines()[-1]
    with tarfile.open(sdist) as tar:
        assert not [m.name for m in tar.getmembers() if m.issym() or m.islnk()]
        tar.extractall(tmp_path / "sdist", filter="data")
    (source,) = (tmp_path / "sdist").iterdir()
    _check_wheel(_pip_wheel(source, tmp_path / "wheel"))
