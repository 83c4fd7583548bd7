"""The house as its imports draw it: packages depend one way, and no modules import each
other in a circle (the README's "Dependencies point one way" and DESIGN.md)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# Each package may import the ones before it, never one after it.
ORDER = ["hardware", "mapping", "slam", "control", "experiments"]


def modules() -> dict[str, Path]:
    out = {}
    for pkg in ORDER:
        for f in (ROOT / pkg).rglob("*.py"):
            name = ".".join(f.relative_to(ROOT).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = f
    return out


def imports(name: str, path: Path, known: set[str]) -> set[str]:
    """Project modules that `name` imports (anywhere in the file, functions included)."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parts, base] if base else parts)
            targets = [base] + [f"{base}.{a.name}" for a in node.names]
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and node.func.id == "__import__"
            and node.args
            and isinstance(node.args[0], ast.Constant)
        ):
            targets = [node.args[0].value]
        for t in targets:
            while t and t not in known:
                t = t.rpartition(".")[0]
            if t and t != name:
                found.add(t)
    return found


def graph() -> dict[str, set[str]]:
    mods = modules()
    return {m: imports(m, f, set(mods)) for m, f in mods.items()}


def test_packages_depend_one_way():
    bad = []
    for mod, deps in graph().items():
        rank = ORDER.index(mod.split(".")[0])
        for d in deps:
            if ORDER.index(d.split(".")[0]) > rank:
                bad.append(f"{mod} imports {d}")
    assert not bad, "imports against the package order:\n" + "\n".join(sorted(bad))


def test_no_module_imports_itself_through_others():
    g = graph()
    circles, seen = [], set()

    def visit(node, path, on_path):
        for d in sorted(g.get(node, ())):
            if d in on_path:
                cycle = path[path.index(d) :]
                key = frozenset(cycle)
                if key not in seen:
                    seen.add(key)
                    circles.append(" -> ".join([*cycle, d]))
            elif d not in done:
                visit(d, [*path, d], on_path | {d})
        done.add(node)

    done: set[str] = set()
    for m in sorted(g):
        if m not in done:
            visit(m, [m], {m})
    assert not circles, "import circles:\n" + "\n".join(circles)
