"""The repository's modules, their layers (docs/internals.md, "The layers") and who imports whom, read
statically from the source: every import statement at any depth counts, inside functions and under
`if TYPE_CHECKING:` too (an annotation is a dependency as much as a call), relative imports resolved.

Used by tests/test_docs_symbols.py (the table of layers) and tests/test_base_layer.py (no cycle).
"""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_DIRS = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
LAYERS = ("base", "drivers", "simulator", "solver", "exports", "server", "commands")


def module_files(package_dirs: dict[str, str] = PACKAGE_DIRS, root: Path = ROOT) -> dict[str, Path]:
    """Dotted module name → file, for every module of the packages `package_dirs` maps to folders of `root`
    (pyproject's package-dir by default)."""
    out = {}
    for pkg, folder in package_dirs.items():
        base = root / folder
        for path in sorted(base.rglob("*.py")):
            rel = path.relative_to(base).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            if any(not (base / Path(*rel.parts[:k]) / "__init__.py").exists() for k in range(1, len(rel.parts))):
                continue  # a folder that is no package (or another package-dir's)
            if rel.name == "__main__":
                continue  # importing it runs the command line
            name = ".".join([pkg, *parts])
            out.setdefault(name, path)
    return out


def layer_of(module: str) -> str | None:
    """The layer of a dotted module name of this repository (None: not ours)."""
    parts = module.split(".")
    if parts[0] != "flockcal":
        return None
    if len(parts) > 1 and parts[1] in LAYERS:
        return parts[1]
    return "commands" if len(parts) > 1 and parts[1] in ("cli", "__main__") else "base"


def imported_modules(tree: ast.AST, module: str = "", is_package: bool = False, known: frozenset = frozenset()) -> set[str]:
    """Every module an import statement of `tree` (the source of `module`) names, at any depth.

    `from a import b` names `a.b` when that is a module of `known`, else `a`; a relative import is
    resolved against `module` (a package's `__init__` when `is_package`)."""
    out: set[str] = set()
    here = module.split(".") if is_package else module.split(".")[:-1]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here[: len(here) - (node.level - 1)] if node.level > 1 else here
                source = ".".join([*base, *([node.module] if node.module else [])])
            else:
                source = node.module or ""
            for alias in node.names:
                sub = f"{source}.{alias.name}"
                out.add(sub if sub in known else source)
    return out


def import_edges(package_dirs: dict[str, str] = PACKAGE_DIRS, root: Path = ROOT) -> dict[tuple[str, str], list[str]]:
    """{(layer, other layer): ["module imports other", …]} for every import that crosses layers."""
    files = module_files(package_dirs, root)
    known = frozenset(files)
    edges: dict[tuple[str, str], list[str]] = {}
    for name, path in files.items():
        own = layer_of(name)
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for mod in sorted(imported_modules(tree, name, path.name == "__init__.py", known)):
            other = layer_of(mod)
            if other not in (None, own):
                edges.setdefault((own, other), []).append(f"{name} imports {mod}")
    return edges


def layer_cycles(edges) -> list[list[str]]:
    """The groups of layers that import each other round a cycle (strongly connected, two or more)."""
    graph: dict[str, set[str]] = {}
    for a, b in edges:
        graph.setdefault(a, set()).add(b)
        graph.setdefault(b, set())

    def reach(start: str) -> set[str]:
        seen, todo = set(), [start]
        while todo:
            for nxt in graph[todo.pop()]:
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        return seen

    within = {a: reach(a) for a in graph}
    groups = {frozenset(b for b in graph if b in within[a] and a in within[b]) | {a} for a in graph if a in within[a]}
    return sorted(sorted(g) for g in groups if len(g) > 1)
