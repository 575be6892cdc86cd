"""The package's shape: imports run one way, every module is a room a newcomer can read, and
every test file one a reader can hold.

Read from the source with `ast`, counting every import: top-level, type-only (under
`if TYPE_CHECKING:`) and inside functions. A type-only import is still a dependency a reader
has to follow, and a function-level one is still a dependency at run time.
"""

from __future__ import annotations

import ast
from pathlib import Path

from tests.support.package_imports import PACKAGE, REPO, imported, module_names, planted_package

#: The most lines a module may have; a module of numba kernels (it imports numba) may have
#: more, since a kernel and its plain-array entry point read best side by side.
MAX_MODULE_LINES = 500
MAX_KERNEL_MODULE_LINES = 700
#: Lines a test file may hold: past it, a file is split by topic.
MAX_TEST_FILE_LINES = 800


def import_graph(package_dir: Path) -> dict[str, set[str]]:
    """Each module of the package and the modules of the package it imports."""
    modules = module_names(package_dir)
    known = set(modules)
    graph = {}
    for module, path in modules.items():
        targets = set()
        for _, name in imported(path, module, known):
            # `from links_ray.a import b` names the module `links_ray.a.b`, or a name in `a`.
            while name and name not in known:
                name = name.rpartition(".")[0]
            if name and name != module:
                targets.add(name)
        graph[module] = targets
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    order: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(start: str) -> None:
        # Iterative, so that a long chain of imports cannot exhaust Python's stack.
        work = [(start, iter(sorted(graph[start])))]
        order[start] = low[start] = len(order)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, successors = work[-1]
            for successor in successors:
                if successor not in order:
                    order[successor] = low[successor] = len(order)
                    stack.append(successor)
                    on_stack.add(successor)
                    work.append((successor, iter(sorted(graph[successor]))))
                    break
                if successor in on_stack:
                    low[node] = min(low[node], order[successor])
            else:
                work.pop()
                if work:
                    parent = work[-1][0]
                    low[parent] = min(low[parent], low[node])
                if low[node] == order[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))

    for module in sorted(graph):
        if module not in order:
            visit(module)
    return sorted(found)


def test_no_module_imports_itself_back() -> None:
    assert cycles(import_graph(REPO / PACKAGE)) == []


def test_the_cycle_check_finds_a_planted_circle(tmp_path: Path) -> None:
    sources = {
        "__init__.py": "",
        "engine/__init__.py": "",
        "engine/a.py": "from links_ray.engine.b import f\n",
        "engine/b.py": (
            "from typing import TYPE_CHECKING\n\nif TYPE_CHECKING:\n"
            "    from links_ray.engine.c import C\n"
        ),
        "engine/c.py": "def g():\n    from links_ray.engine import a\n",
        "engine/d.py": "from links_ray.engine import a, b\n",
        "serve/__init__.py": "",
        "serve/x.py": "from . import y\n",
        "serve/y.py": "import links_ray.serve.x\n",
    }
    planted_package(tmp_path, sources)
    assert cycles(import_graph(tmp_path / PACKAGE)) == [
        ["links_ray.engine.a", "links_ray.engine.b", "links_ray.engine.c"],
        ["links_ray.serve.x", "links_ray.serve.y"],
    ]


def imports_numba(path: Path) -> bool:
    """Whether the module imports numba (at its top level): a module of compiled kernels."""
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in tree.body:
        if isinstance(node, ast.Import) and any(
            alias.name.split(".")[0] == "numba" for alias in node.names
        ):
            return True
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "numba":
            return True
    return False


def test_every_module_is_a_room_of_readable_size() -> None:
    too_long = []
    for module, path in module_names(REPO / PACKAGE).items():
        lines = len(path.read_text().splitlines())
        limit = MAX_KERNEL_MODULE_LINES if imports_numba(path) else MAX_MODULE_LINES
        if lines > limit:
            too_long.append(f"{module}: {lines} lines (at most {limit})")
    assert too_long == []


def test_every_folder_of_modules_is_a_package() -> None:
    """A folder of modules without `__init__.py` is a namespace package, which the wheel's
    package search leaves out: its modules would be missing from an installed links-ray."""
    folders = {path.parent for path in (REPO / PACKAGE).rglob("*.py")}
    assert (
        sorted(str(f.relative_to(REPO)) for f in folders if not (f / "__init__.py").is_file()) == []
    )


def test_every_test_file_is_of_readable_size() -> None:
    too_long = [
        f"{path.relative_to(REPO)}: {lines} lines (at most {MAX_TEST_FILE_LINES})"
        for path in sorted((REPO / "tests").rglob("*.py"))
        if (lines := len(path.read_text().splitlines())) > MAX_TEST_FILE_LINES
    ]
    assert too_long == []


def test_the_files_the_workers_take_first_exist() -> None:
    """tests/support/workers.py names test files to hand out first: a renamed or removed file
    would drop out of that order unnoticed."""
    from tests.support.workers import LONGEST_FIRST

    missing = [path for path in LONGEST_FIRST if not (REPO / path).is_file()]
    assert not missing, missing
    assert len(set(LONGEST_FIRST)) == len(LONGEST_FIRST)
