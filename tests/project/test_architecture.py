"""The architecture page's module table lists every module of the package, once, and nothing
else, so that it cannot fall behind the code."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PAGE = REPO / "docs" / "design" / "architecture.md"


def package_modules() -> set[str]:
    """Every module of links_ray as the table names it (`engine/kinematics/solver`), packages' own
    `__init__` and `__main__` aside."""
    package = REPO / "links_ray"
    return {
        path.relative_to(package).with_suffix("").as_posix()
        for path in package.rglob("*.py")
        if path.name not in ("__init__.py", "__main__.py")
    }


def tabled_modules(text: str) -> list[str]:
    """The modules named in the first cell of the page's module table, in order."""
    start = text.index("## Modules")
    rows = [line for line in text[start:].splitlines() if line.startswith("| `")]
    named = []
    for row in rows:
        first = row.split("|")[1]
        named += [name for name in re.findall(r"`([^`]+)`", first) if not name.endswith("/")]
    return named


def test_the_module_table_names_every_module_once() -> None:
    named = tabled_modules(PAGE.read_text())
    repeated = sorted({name for name in named if named.count(name) > 1})
    assert repeated == [], f"named twice: {repeated}"
    assert sorted(package_modules() - set(named)) == [], "modules missing from the table"
    assert sorted(set(named) - package_modules()) == [], "table rows for no module"


def test_the_table_check_sees_a_missing_and_a_stale_row() -> None:
    page = "## Modules\n\n| module | layer | what |\n|---|---|---|\n"
    page += "| `engine/kinematics/solver` | engine | x |\n"
    assert tabled_modules(page) == ["engine/kinematics/solver"]
    assert "engine/kinematics/paths" in package_modules() - set(tabled_modules(page))
    stale = page + "| `engine/gone`, `engine/kinematics/solver` | engine | y |\n"
    assert tabled_modules(stale) == [
        "engine/kinematics/solver",
        "engine/gone",
        "engine/kinematics/solver",
    ]
