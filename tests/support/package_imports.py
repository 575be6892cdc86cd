"""The package's modules and their imports, read from the source with `ast` (tests/project's
layer and structure checks share them)."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PACKAGE = "links_ray"


def module_names(package_dir: Path) -> dict[str, Path]:
    """Every module under `package_dir` by dotted name (a package by its `__init__.py`)."""
    names = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = path.relative_to(package_dir.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names[".".join(parts)] = path
    return names


def imported(path: Path, module: str, known: set[str]) -> list[tuple[int, str]]:
    """(line, dotted name) of everything `path` imports, at any depth, relative ones resolved.

    `from a import b` counts as importing `a.b` when that is a module of ours, else `a`;
    `importlib.import_module("name")` with a constant name counts too.
    """
    tree = ast.parse(path.read_text(), filename=str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                candidate = f"{base}.{alias.name}"
                found.append((node.lineno, candidate if candidate in known else base))
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            found.append((node.lineno, node.args[0].value))
    return found


def planted_package(root: Path, sources: dict[str, str]) -> Path:
    """A small package shaped like ours under `root`, its modules' text by path
    (`"engine/solver.py"`), for the checks of the imports to fail on; returns its folder."""
    for name, text in sources.items():
        path = root / PACKAGE / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root / PACKAGE
