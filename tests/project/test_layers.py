"""The package's layers hold: a module imports only its own layer or lower ones.

engine (numpy/numba) < data (pyarrow), interop (other libraries, drawing files) < search,
cluster, release (the LINKS release's own files) < serve < cli < bench, where data and interop
are peers, and so are search, cluster and release (none of them imports another). Of the layers
above it, only cli and bench import release. `links_ray/__init__.py` may import engine and data
only, but for `links_ray.ray_dataset`, which it loads from the cluster layer when first asked
for (so that `import links_ray` still loads no Ray: `test_import_links_ray_loads_no_ray`); and
the command line loads the benchmarks only for `links bench`. The engine and interop import no
Ray, pyarrow or pandas; data, search and release import no Ray, nor does the HTTP layer
(`serve.http`). Inside the engine, kinematics < fabrication < synthesis over a shared base.
Read from the source with `ast`, imports inside functions included: a lazy import is still a
dependency."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.package_imports import PACKAGE, REPO, imported, module_names, planted_package

#: Rank of each layer: a module may import its own layer and layers of lower rank.
LAYERS = {
    "engine": 0,
    "data": 1,
    "interop": 1,
    "search": 2,
    "cluster": 2,
    "release": 2,
    "serve": 3,
    "cli": 4,
    "bench": 5,
}
#: Layers only some of the layers above them may import: the release's files are the
#: command line's business (`links import-release`, `links export-dataset --format release`)
#: and the benchmarks' (the unpickler's fuzzing).
IMPORTED_ONLY_BY = {"release": ("cli", "bench")}
#: What the package's own `__init__.py` (`import links_ray`) may load.
ROOT_MAY_IMPORT = ("engine", "data")
#: Modules the package's own `__init__.py` may load lazily, on first use of a name.
ROOT_LAZY = ("links_ray.cluster.datasets",)
#: The one import of a layer above: `links bench` loads the benchmarks' room (which uses the
#: command line's helpers) only when asked for, in the command line's `main`.
UPWARD_LAZY = {"links_ray.cli.main": ("links_ray.bench.command",)}
#: Third-party packages a layer must not import, even lazily.
FORBIDDEN = {
    "root": ("ray",),
    "engine": ("ray", "pyarrow", "pandas"),
    "data": ("ray",),
    "interop": ("ray", "pyarrow", "pandas"),
    "search": ("ray",),
    "release": ("ray",),
    "bench": (),
}
#: Subpackages that must not import these, even lazily, though their layer may: the HTTP
#: layer (routes, schemas, bodies, responses, middleware, admission, limits, the gate) needs no
#: Ray; only the Serve deployments and the application around it do.
FORBIDDEN_UNDER = {"links_ray.serve.http": ("ray",)}


def forbidden_in(module: str) -> tuple[str, ...]:
    """What `module` must not import because of the subpackage it is in."""
    return tuple(
        name
        for package, names in FORBIDDEN_UNDER.items()
        if module == package or module.startswith(f"{package}.")
        for name in names
    )


def layer_of(module: str) -> str | None:
    """The layer a dotted name of ours lives in: "root" for the package itself, and the
    command line's for `links_ray.__main__` (`python -m links_ray` is the `links` command)."""
    parts = module.split(".")
    if parts[0] != PACKAGE:
        return None
    if parts[1:] == ["__main__"]:
        return "cli"
    return "root" if len(parts) == 1 else parts[1]


def may_import(own: str, target: str) -> bool:
    """Whether layer `own` may import from layer `target`."""
    if own == "root":
        return target in ROOT_MAY_IMPORT
    if target == "root":  # `import links_ray` loads engine and data
        return all(may_import(own, layer) for layer in ROOT_MAY_IMPORT)
    if own not in LAYERS or target not in LAYERS:
        return False
    if target != own and own not in IMPORTED_ONLY_BY.get(target, (own,)):
        return False
    return target == own or LAYERS[target] < LAYERS[own]


def violations(package_dir: Path) -> list[str]:
    """Every import that breaks the layer rule, as `file:line: what`."""
    modules = module_names(package_dir)
    problems = []
    for module, path in modules.items():
        where = path.relative_to(package_dir.parent)
        own = layer_of(module)
        if own != "root" and own not in LAYERS:
            problems.append(f"{where}: in no layer")
            continue
        for line, name in imported(path, module, set(modules)):
            top = name.split(".")[0]
            if top in FORBIDDEN.get(own, ()) + forbidden_in(module):
                problems.append(f"{where}:{line}: {own} imports {name}")
            target = layer_of(name)
            if own == "root" and name in ROOT_LAZY:
                continue
            if name in UPWARD_LAZY.get(module, ()):
                continue
            if target is not None and not may_import(own, target):
                problems.append(f"{where}:{line}: {own} imports {name} ({target})")
    return problems


def test_every_import_goes_to_its_own_layer_or_lower() -> None:
    assert set(FORBIDDEN_UNDER) <= set(module_names(REPO / PACKAGE))
    assert violations(REPO / PACKAGE) == []


def test_import_links_ray_loads_no_ray() -> None:
    probe = (
        "import sys, links_ray\n"
        "print(sorted(m for m in sys.modules if m == 'ray' or m.startswith('ray.'))[:5])"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}  # this checkout, whatever is installed
    done = subprocess.run(
        [sys.executable, "-c", probe], cwd=REPO, env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


@pytest.fixture
def broken_package(tmp_path: Path) -> Path:
    """A small package shaped like ours, one module per kind of violation."""
    sources = {
        "__init__.py": "from .engine import solver\nfrom .search import index\nimport ray\n",
        "engine/__init__.py": "",
        "engine/solver.py": "def f():\n    import ray.util\n    from links_ray import data\n",
        "data/__init__.py": "",
        "data/store.py": "import pyarrow\nfrom ..search.index import g\n",
        "search/__init__.py": "",
        "search/index.py": (
            "import importlib\n\n\ndef g():\n    importlib.import_module('links_ray.cluster.run')\n"
        ),
        "cluster/__init__.py": "",
        "cluster/run.py": "from links_ray.search import index\nimport ray\n",
        "serve/__init__.py": "",
        "serve/app.py": "import links_ray\nfrom links_ray.cli import main\n",
        "serve/http/__init__.py": "",
        "serve/http/bodies.py": "def f():\n    from ray import serve\n",
        "serve/export.py": "from links_ray.release import exporter\n",
        "release/__init__.py": "",
        "release/exporter.py": "from links_ray.search import index\nimport ray\n",
        "cli/__init__.py": "",
        "cli/main.py": (
            "import links_ray\nfrom links_ray.serve import app\nfrom . import main\n"
            "from links_ray.release import exporter\n"
        ),
        "stray.py": "import numpy\n",
    }
    return planted_package(tmp_path, sources)


def test_the_rule_catches_what_breaks_it(broken_package: Path) -> None:
    assert violations(broken_package) == [
        "links_ray/__init__.py:2: root imports links_ray.search.index (search)",
        "links_ray/__init__.py:3: root imports ray",
        "links_ray/cluster/run.py:1: cluster imports links_ray.search.index (search)",
        "links_ray/data/store.py:2: data imports links_ray.search.index (search)",
        "links_ray/engine/solver.py:2: engine imports ray.util",
        "links_ray/engine/solver.py:3: engine imports links_ray.data (data)",
        "links_ray/release/exporter.py:1: release imports links_ray.search.index (search)",
        "links_ray/release/exporter.py:2: release imports ray",
        "links_ray/search/index.py:5: search imports links_ray.cluster.run (cluster)",
        "links_ray/serve/app.py:2: serve imports links_ray.cli.main (cli)",
        "links_ray/serve/export.py:1: serve imports links_ray.release.exporter (release)",
        "links_ray/serve/http/bodies.py:2: serve imports ray",
        "links_ray/stray.py: in no layer",
    ]


#: A package's face (the module its callers import) and the package of the rooms behind it:
#: a room never imports its face, not even for type hints (`if TYPE_CHECKING:`), so that
#: imports run one way, face to rooms (the face passes the rooms plain arrays).
FACES = {"links_ray.search.index": "links_ray.search"}


def face_violations(package_dir: Path) -> list[str]:
    """Every import of a face by one of its rooms, type hints' included."""
    modules = module_names(package_dir)
    known = set(modules)
    found = []
    for face, package in FACES.items():
        for module, path in modules.items():
            if module == face or not module.startswith(f"{package}."):
                continue
            for line, name in imported(path, module, known):
                if name == face:
                    where = path.relative_to(package_dir.parent).as_posix()
                    found.append(f"{where}:{line}: {module} imports its face {face}")
    return sorted(found)


def test_rooms_never_import_their_face() -> None:
    assert face_violations(REPO / PACKAGE) == []


def test_the_face_rule_catches_a_room_importing_its_face(tmp_path: Path) -> None:
    sources = {
        "__init__.py": "",
        "search/__init__.py": "",
        "search/index.py": "from links_ray.search import query\n",
        "search/query.py": (
            "from typing import TYPE_CHECKING\n\nif TYPE_CHECKING:\n"
            "    from links_ray.search.index import RetrievalIndex\n"
        ),
        "search/build.py": "def f():\n    from links_ray.search import index\n",
    }
    planted_package(tmp_path, sources)
    assert face_violations(tmp_path / PACKAGE) == [
        "links_ray/search/build.py:2: links_ray.search.build imports its face "
        "links_ray.search.index",
        "links_ray/search/query.py:4: links_ray.search.query imports its face "
        "links_ray.search.index",
    ]


def test_the_http_layer_never_imports_the_serve_assembly() -> None:
    """The HTTP layer (`serve.http`) never imports the Serve deployments or the application
    built from them, and its routes never import the ASGI app that takes them in: the assembly
    takes the layer in. No circle anywhere is tests/project/test_structure.py's."""
    modules = module_names(REPO / PACKAGE)
    assembly = {"links_ray.serve.deployments", "links_ray.serve.app"}
    http = [module for module in modules if module.startswith("links_ray.serve.http.")]
    assert "links_ray.serve.http.routes" in http
    for module in http:
        imports = {name for _, name in imported(modules[module], module, set(modules))}
        assert not imports & assembly, module
        if module != "links_ray.serve.http.asgi":
            assert "links_ray.serve.http.asgi" not in imports, module


#: The engine's rooms in order: a room imports the base (`engine.<module>`) and the rooms
#: before it, never one after it; the base imports no room.
ENGINE_ROOMS = ("kinematics", "fabrication", "synthesis")


def engine_room_of(module: str) -> int | None:
    """The rank of an engine module's room: 0 for the base, 1 to 3 for the rooms in order,
    None outside the engine."""
    parts = module.split(".")
    if parts[:2] != [PACKAGE, "engine"]:
        return None
    if len(parts) > 3 and parts[2] in ENGINE_ROOMS:
        return 1 + ENGINE_ROOMS.index(parts[2])
    if len(parts) == 3 and parts[2] in ENGINE_ROOMS:  # a room's own face
        return 1 + ENGINE_ROOMS.index(parts[2])
    return 0


def engine_room_violations(package_dir: Path) -> list[str]:
    """Every import, by an engine module, of an engine room after its own."""
    modules = module_names(package_dir)
    problems = []
    for module, path in modules.items():
        own = engine_room_of(module)
        if own is None or module == f"{PACKAGE}.engine":
            continue
        for line, name in imported(path, module, set(modules)):
            target = engine_room_of(name)
            if target is not None and target > own:
                where = path.relative_to(package_dir.parent).as_posix()
                problems.append(f"{where}:{line}: {module} imports {name}")
    return sorted(problems)


def test_the_engine_rooms_import_only_the_rooms_before_them() -> None:
    modules = set(module_names(REPO / PACKAGE))
    for room in ENGINE_ROOMS:
        assert f"{PACKAGE}.engine.{room}" in modules
    assert engine_room_violations(REPO / PACKAGE) == []


def test_the_engine_room_rule_catches_an_import_upward(tmp_path: Path) -> None:
    sources = {
        "__init__.py": "",
        "engine/__init__.py": "",
        "engine/inputs.py": "from links_ray.engine.kinematics import solver\n",
        "engine/kinematics/__init__.py": "",
        "engine/kinematics/solver.py": "from links_ray.engine import inputs\n",
        "engine/fabrication/__init__.py": "",
        "engine/fabrication/kit.py": (
            "from links_ray.engine.kinematics import solver\n"
            "def f():\n    from links_ray.engine.synthesis import pipeline\n"
        ),
        "engine/synthesis/__init__.py": "",
        "engine/synthesis/pipeline.py": "from links_ray.engine.fabrication import kit\n",
    }
    planted_package(tmp_path, sources)
    assert engine_room_violations(tmp_path / PACKAGE) == [
        "links_ray/engine/fabrication/kit.py:3: links_ray.engine.fabrication.kit imports "
        "links_ray.engine.synthesis.pipeline",
        "links_ray/engine/inputs.py:1: links_ray.engine.inputs imports "
        "links_ray.engine.kinematics.solver",
    ]
