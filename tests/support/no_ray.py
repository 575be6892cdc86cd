"""A pytest plugin that makes `import ray` fail: the engine's tests run where Ray is absent.

    python -m pytest -p tests.support.no_ray tests/engine

tests/run runs tests/engine this way, in a pytest process of its own. The finder is installed
when the plugin loads, before any test module is imported, and refuses `ray` and every
`ray.*` module as an uninstalled package would (ImportError, ModuleNotFoundError's base).
A Ray that some earlier import already loaded is an error here, not a pass.
"""

from __future__ import annotations

import sys
from importlib.abc import MetaPathFinder


class NoRay(MetaPathFinder):
    """Refuses `ray` and its submodules."""

    def find_spec(self, name: str, path: object = None, target: object = None) -> None:
        if name == "ray" or name.startswith("ray."):
            raise ModuleNotFoundError(f"No module named {name!r} (tests.support.no_ray)", name=name)
        return None


if any(name == "ray" or name.startswith("ray.") for name in sys.modules):
    raise RuntimeError("tests.support.no_ray: Ray was imported before the plugin loaded")
sys.meta_path.insert(0, NoRay())


def pytest_report_header() -> str:
    return "Ray blocked: `import ray` fails (tests.support.no_ray)"
