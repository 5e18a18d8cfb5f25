"""egcbf's folders form layers: a module imports only modules of its own folder or of folders below it in
:data:`LAYERS` (module-level and function-level imports alike), and the package root holds nothing but its face.

The order is the one docs/architecture.md draws; a new folder must be placed in it before it can be imported."""

from test_import_cycles import SRC, _graph

#: egcbf's top-level folders (and root modules), from the bottom up
LAYERS = (
    "_version",
    "io",
    "geometry",
    "qp",
    "robots",
    "env",
    "faults",
    "nn",
    "algo",
    "evaluate",
    "train",
    "marl",
    "control",
    "deploy",
    "ros",
    "viz",
    "reproduce",
    "study",
    "robustness",
    "certify",
    "cli",
    "__main__",
)
ROOT_FILES = {"__init__.py", "__main__.py", "_version.py"}


def _layer(module: str) -> str | None:
    """The layer of an egcbf module (``None`` for the package itself and for other packages)."""
    parts = module.split(".")
    return parts[1] if parts[0] == "egcbf" and len(parts) > 1 else None


def upward_imports(graph: dict[str, set[str]], layers: tuple[str, ...] = LAYERS) -> list[str]:
    """``"a -> b"`` for every import of ``graph`` from a layer to one above it, or to an undeclared layer."""
    rank = {name: k for k, name in enumerate(layers)}
    bad = []
    for module, targets in sorted(graph.items()):
        here = _layer(module)
        for target in sorted(targets):
            there = _layer(target)
            if here is None or there is None or there == here:
                continue
            if here not in rank or there not in rank or rank[there] > rank[here]:
                bad.append(f"{module} -> {target}")
    return bad


def test_no_import_points_up_the_layers():
    bad = upward_imports(_graph())
    assert not bad, "imports pointing up the layers (tests/test_layer_order.py::LAYERS):\n" + "\n".join(bad)


def test_every_folder_has_a_layer_and_the_root_holds_only_its_face():
    root = SRC / "egcbf"
    folders = {p.name for p in root.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert folders <= set(LAYERS), f"folders without a layer: {sorted(folders - set(LAYERS))}"
    files = {p.name for p in root.glob("*.py")}
    assert files == ROOT_FILES, f"modules at egcbf's root besides its face: {sorted(files - ROOT_FILES)}"


def test_the_checker_finds_an_upward_import():
    graph = {"egcbf.robots.x": {"egcbf.env.swarm", "egcbf.qp.ipm"}, "egcbf.env.swarm": {"egcbf.robots.x"}}
    assert upward_imports(graph) == ["egcbf.robots.x -> egcbf.env.swarm"]
    assert upward_imports({"egcbf.newfolder.a": {"egcbf.io.atomic"}}) == ["egcbf.newfolder.a -> egcbf.io.atomic"]
    assert upward_imports({"egcbf.cli.a": {"egcbf.cli.b", "torch"}}) == []


def test_docs_architecture_draws_the_same_order():
    """docs/architecture.md's drawing lists the folders from the top down: the reverse of :data:`LAYERS`."""
    import re

    text = (SRC.parent / "docs" / "architecture.md").read_text()
    drawing = text.split("```")[1]
    drawn = [m.group(1) for m in re.finditer(r"^ (\w+)/ ", drawing, re.MULTILINE)]
    assert drawn == [name for name in reversed(LAYERS) if name not in ("_version", "__main__")]


def test_no_branch_on_a_robots_name_outside_robots():
    """Outside ``egcbf.robots`` the code asks a robot what it can do (its declared capabilities), never which robot
    it is: no comparison (``==``, ``!=``, ``in``) with a built-in robot's name."""
    import ast

    names = {"quadrotor", "unicycle", "single_integrator", "double_integrator", "linear_drone", "dubins_car"}
    bad = []
    for path in (SRC / "egcbf").rglob("*.py"):
        if "robots" in path.relative_to(SRC / "egcbf").parts:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Compare):
                for side in (node.left, *node.comparators):
                    if isinstance(side, ast.Constant) and side.value in names:
                        bad.append(f"{path.relative_to(SRC)}:{node.lineno}")
    assert not bad, bad
