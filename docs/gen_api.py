"""Generate docs/api.md, the API reference of groupcanon, from the source's docstrings and signatures.

    .venv/bin/python docs/gen_api.py           # rewrite docs/api.md
    .venv/bin/python docs/gen_api.py --check   # exit 1 if docs/api.md is out of date

The source is parsed (``ast``), not imported, so the output does not depend on which optional extras (escnn) are
installed. A module's public names are its ``__all__``; for classes, every public method and property defined in
the class body is listed (methods a subclass overrides without a docstring point to the base class's).
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "src" / "groupcanon"
OUT = ROOT / "docs" / "api.md"

# Reading order; modules not listed here are appended alphabetically, so new files are never missed.
ORDER = [
    "__init__.py",
    "group.py",
    "groups/__init__.py",
    "groups/so2.py",
    "groups/cyclic.py",
    "groups/o2.py",
    "groups/se2.py",
    "groups/so3.py",
    "groups/translation.py",
    "groups/product.py",
    "groups/trivial.py",
    "features.py",
    "field_type.py",
    "canonicalize.py",
    "frames.py",
    "testing/__init__.py",
    "testing/checks.py",
    "testing/strategies.py",
]


def module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def modules() -> list[Path]:
    files = [p for p in PKG.rglob("*.py") if not p.name.startswith("_") or p.name == "__init__.py"]
    files = [p for p in files if "__pycache__" not in p.parts]
    rel = {p.relative_to(PKG).as_posix(): p for p in files}
    ordered = [rel.pop(k) for k in ORDER if k in rel]
    return ordered + [rel[k] for k in sorted(rel)]


def public_names(tree: ast.Module) -> list[str] | None:
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
            return [ast.literal_eval(e) for e in node.value.elts]
    return None


def signature(fn: ast.FunctionDef, drop_self: bool) -> str:
    args = fn.args
    if drop_self and args.args and args.args[0].arg in ("self", "cls"):
        args = ast.arguments(
            posonlyargs=args.posonlyargs,
            args=args.args[1:],
            vararg=args.vararg,
            kwonlyargs=args.kwonlyargs,
            kw_defaults=args.kw_defaults,
            kwarg=args.kwarg,
            defaults=args.defaults,  # defaults align with the last arguments, so dropping the first changes nothing
        )
    text = ast.unparse(args)
    ret = f" -> {ast.unparse(fn.returns)}" if fn.returns is not None else ""
    return f"({text}){ret}"


def decorators(fn: ast.FunctionDef) -> set[str]:
    return {ast.unparse(d) for d in fn.decorator_list}


def doc_block(node, indent: str = "") -> list[str]:
    doc = ast.get_docstring(node)
    if not doc:
        return []
    return [indent + line if line else "" for line in doc.splitlines()] + [""]


def render_function(fn: ast.FunctionDef, prefix: str) -> list[str]:
    out = [f"### `{prefix}{fn.name}{signature(fn, drop_self=False)}`", ""]
    return out + (doc_block(fn) or ["(no docstring)", ""])


def class_attributes(cls: ast.ClassDef) -> list[str]:
    """Public class-level attributes with a ``#:`` comment or an annotation."""
    out = []
    for node in cls.body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and not node.target.id.startswith("_"):
            value = f" = {ast.unparse(node.value)}" if node.value is not None else ""
            out.append(f"`{node.target.id}: {ast.unparse(node.annotation)}{value}`")
        elif isinstance(node, ast.Assign):
            for t in node.targets:
                if isinstance(t, ast.Name) and not t.id.startswith("_"):
                    out.append(f"`{t.id} = {ast.unparse(node.value)}`")
    return out


def find_init(cls: ast.ClassDef, defs: dict) -> ast.FunctionDef | None:
    """``__init__`` of ``cls`` or of the nearest base class defined in the same module."""
    init = next((n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name == "__init__"), None)
    if init is None:
        for b in cls.bases:
            base = defs.get(ast.unparse(b))
            if isinstance(base, ast.ClassDef) and (init := find_init(base, defs)) is not None:
                break
    return init


def render_class(cls: ast.ClassDef, modname: str, defs: dict) -> list[str]:
    bases = ", ".join(ast.unparse(b) for b in cls.bases if ast.unparse(b) not in ("object",))
    init = find_init(cls, defs)
    sig = signature(init, drop_self=True).split(" -> ")[0] if init else ""
    out = [f"### class `{modname}.{cls.name}{sig}`" + (f" ({bases})" if bases else ""), ""]
    out += doc_block(cls) or ["(no docstring)", ""]
    attrs = class_attributes(cls)
    if attrs:
        out += ["Attributes: " + ", ".join(attrs), ""]
    members = []
    for node in cls.body:
        if not isinstance(node, ast.FunctionDef):
            continue
        name = node.name
        if name.startswith("_") and name not in ("__call__",):
            continue
        decos = decorators(node)
        if "property" in decos or any(d.endswith(".setter") for d in decos):
            if any(d.endswith(".setter") for d in decos):
                continue
            head = f"- property `{name}`"
            if node.returns is not None:
                head += f" -> `{ast.unparse(node.returns)}`"
        else:
            kind = "staticmethod " if "staticmethod" in decos else "classmethod " if "classmethod" in decos else ""
            head = f"- {kind}`{name}{signature(node, drop_self=not kind.startswith('static'))}`"
        if "abc.abstractmethod" in decos or "abstractmethod" in decos:
            head += " *(abstract)*"
        doc = ast.get_docstring(node)
        if doc:
            first, *rest = doc.splitlines()
            members.append(f"{head}: {first}")
            members += [f"  {line}" if line else "" for line in rest if line.strip()]
        else:
            ours = any(ast.unparse(b).split(".")[-1] in OUR_CLASSES for b in cls.bases)
            members.append(f"{head}: " + ("see the base class" if ours else "see the class docstring"))
    if members:
        out += [*members, ""]
    return out


def render_module(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    name = module_name(path)
    out = [f"## `{name}`", "", f"Source: `src/{path.relative_to(PKG.parent).as_posix()}`", ""]
    out += doc_block(tree)
    names = public_names(tree)
    defs = {n.name: n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
    if path.name == "__init__.py":
        if names:
            out += ["Exports: " + ", ".join(f"`{n}`" for n in names), ""]
        return out
    if names is None:
        names = [n for n in defs if not n.startswith("_")]
    for n in names:
        node = defs.get(n)
        if isinstance(node, ast.ClassDef):
            out += render_class(node, name, defs)
        elif isinstance(node, ast.FunctionDef):
            out += render_function(node, f"{name}.")
    return out


OUR_CLASSES: set[str] = set()  # classes defined in groupcanon (filled by generate)


def generate() -> str:
    for p in modules():
        OUR_CLASSES.update(n.name for n in ast.walk(ast.parse(p.read_text())) if isinstance(n, ast.ClassDef))
    out = [
        "# groupcanon API reference",
        "",
        "Generated by `docs/gen_api.py` from the docstrings and signatures in `src/groupcanon` (do not edit by",
        "hand: run `.venv/bin/python docs/gen_api.py`). The guide is [groupcanon.md](groupcanon.md).",
        "",
        "Conventions used throughout: a group element is a plain tensor `(*batch, *G.element_shape)` whose leading",
        "dimensions are batch dimensions; features are `(*batch, dim)`; batch dimensions broadcast; every operation",
        "is differentiable and keeps dtype and device. Frames are one group element per receiving node,",
        "`(N, *element_shape)`.",
        "",
        "## Contents",
        "",
    ]
    paths = modules()
    for p in paths:
        name = module_name(p)
        out.append(f"- [`{name}`](#{name.replace('.', '')})")
    out.append("")
    for p in paths:
        out += render_module(p)
    text = "\n".join(out)
    while "\n\n\n" in text:
        text = text.replace("\n\n\n", "\n\n")
    return text.rstrip("\n") + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="generate docs/api.md")
    parser.add_argument("--check", action="store_true", help="exit 1 if docs/api.md is out of date")
    args = parser.parse_args(argv)
    text = generate()
    if args.check:
        current = OUT.read_text() if OUT.exists() else ""
        if current != text:
            print(f"{OUT.relative_to(ROOT)} is out of date: run .venv/bin/python docs/gen_api.py")
            return 1
        print(f"{OUT.relative_to(ROOT)} is up to date")
        return 0
    OUT.write_text(text)
    print(f"wrote {OUT.relative_to(ROOT)} ({len(text.splitlines())} lines)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
