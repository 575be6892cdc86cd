"""The tests of the rooms a change touches: `python -m tests.support.changed [BASE]` prints the
test folders and files for the files that differ from BASE (default `main`, and the working
tree's own changes), one a line, for a contributor's quick loop (`tests/run --changed`).

A module of `links_ray/<layer>/<room>/` maps to `tests/<layer>/<room>/` where that folder
exists, else to `tests/<layer>/`; a test file maps to itself, a support module or a conftest
to its folder's tests; docs to the docs' tests. The whole-repository checks that take seconds
(the layers, the structure, the architecture page) always run.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
#: Whole-repository checks of a few seconds, run whatever changed.
ALWAYS = (
    "tests/project/test_layers.py",
    "tests/project/test_structure.py",
    "tests/project/test_architecture.py",
)


def changed_files(base: str) -> list[str]:
    """Files that differ from `base` (committed since it, or changed and not committed)."""
    since = subprocess.run(
        ["git", "diff", "--name-only", f"{base}...HEAD"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    here = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=all"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.splitlines()
    return sorted({*since, *(line[3:].split(" -> ")[-1] for line in here)})


def covering_tests(path: str) -> str | None:
    """The test folder or file that covers `path`, or None."""
    parts = Path(path).parts
    if parts[:1] == ("tests",):
        name = parts[-1]
        if name.startswith("test_") and name.endswith(".py"):
            return path
        if name == "conftest.py" and len(parts) > 2:  # a folder's own fixtures: its tests
            return str(Path(*parts[:-1]))
        return None  # a support module serves many folders: the whole suite is its test
    if parts[:1] == ("links_ray",) and len(parts) > 2:
        for depth in range(len(parts) - 1, 1, -1):
            folder = Path("tests", *parts[1:depth])
            if (REPO / folder).is_dir():
                return str(folder)
        return None
    if parts[:1] == ("docs",) or path == "README.md":
        return "tests/project/test_docs.py"
    if parts[:1] == ("deploy",):
        return "tests/project"
    if parts[:1] == ("notebooks",):
        return "tests/project/test_notebooks.py"
    return None


def main(argv: list[str]) -> int:
    """Print the tests for the files changed since argv[0] (default main)."""
    base = argv[0] if argv else "main"
    targets = {target for path in changed_files(base) if (target := covering_tests(path))}
    targets = {t for t in targets if (REPO / t).exists()}
    # A folder already listed covers the files in it.
    targets |= set(ALWAYS)
    kept = sorted(t for t in targets if not any(t != o and t.startswith(o + "/") for o in targets))
    print("\n".join(kept))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
