"""The quick loop's map from a changed file to its tests (`tests/support/changed.py`)."""

from __future__ import annotations

import pytest

from tests.support.changed import covering_tests


@pytest.mark.parametrize(
    ("path", "tests"),
    [
        ("links_ray/engine/kinematics/solver.py", "tests/engine/kinematics"),
        ("links_ray/engine/synthesis/refinement/kernels.py", "tests/engine/synthesis"),
        ("links_ray/engine/inputs.py", "tests/engine"),
        ("links_ray/serve/http/routes.py", "tests/serve"),
        ("links_ray/bench/curves/curve_set.py", "tests/bench"),
        ("links_ray/data/generation.py", "tests/data"),
        ("tests/engine/kinematics/test_paths.py", "tests/engine/kinematics/test_paths.py"),
        ("tests/engine/conftest.py", "tests/engine"),
        ("docs/guides/synthesis.md", "tests/project/test_docs.py"),
        ("links_ray/__init__.py", None),
        ("pyproject.toml", None),
    ],
)
def test_a_changed_file_maps_to_the_tests_of_its_room(path: str, tests: str | None) -> None:
    assert covering_tests(path) == tests
