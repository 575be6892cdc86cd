"""The suite's one large dataset, where retrieval scans instead of estimating every path: made
once and kept between runs, keyed by the code that makes it.

Entries live under ``<repository>/.cache/test-data/`` (or ``$LINKS_TEST_CACHE``), each a folder
``<name>-<key>``, where the key hashes the sources of the packages that make it and its
parameters. An entry is built in a hidden folder beside it and renamed into place, so a killed
build leaves no half entry (the next build of that key deletes what it left). A lock file per
entry serializes builds of one key across processes: a builder holds it exclusively, a reader
shared while it copies. Once a new entry is in place, the other entries of its name that no one
holds are deleted.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import shutil
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import links_ray

REPOSITORY = Path(__file__).resolve().parents[2]
CACHE = Path(os.environ.get("LINKS_TEST_CACHE") or REPOSITORY / ".cache" / "test-data")
PACKAGE = Path(links_ray.__file__).resolve().parent

#: The dataset: mechanisms only, then curated paths only (what retrieval reads), about 4.2
#: curated paths a mechanism; small shards, so that every split into 2 or 4 parts is even.
GENERATION = {
    "mechanisms": 10_000,
    "seed": 2027,
    "topologies_per_shard": 40,
    "tables": ["mechanisms"],
    "curation_tables": ["curated"],
}
#: Index splits saved in the indexed entry: one index, and the parts of 2 and 4.
SPLITS = (1, 2, 4)


def code_key(packages: tuple[str, ...], parameters: dict) -> str:
    """A hash of the Python sources of these links_ray subpackages and of `parameters`."""
    digest = hashlib.sha256(json.dumps(parameters, sort_keys=True).encode())
    for package in packages:
        for source in sorted((PACKAGE / package).rglob("*.py")):
            digest.update(str(source.relative_to(PACKAGE)).encode() + b"\0")
            digest.update(source.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


def link_tree(source: Path, target: Path) -> None:
    """A copy of folder `source` at `target` whose files are hard links where the file system
    allows (every write of the project replaces a file, never changes one in place), without
    leases."""

    def link(src: str, dst: str) -> None:
        try:
            os.link(src, dst)
        except OSError:
            shutil.copy2(src, dst)

    shutil.copytree(source, target, copy_function=link, ignore=shutil.ignore_patterns("leases"))


@contextlib.contextmanager
def _flock(path: Path, mode: int) -> Iterator[int]:
    descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(descriptor, mode)
        yield descriptor
    finally:
        os.close(descriptor)  # and with it the lock


def _prune(name: str, keep: str) -> None:
    """Delete the entries of `name` other than `keep` that no process holds, and what killed
    builds of them left."""
    for entry in CACHE.glob(f"{name}-*.lock"):
        key = entry.name[len(name) + 1 : -len(".lock")]
        if key == keep:
            continue
        with contextlib.suppress(BlockingIOError), _flock(entry, fcntl.LOCK_EX | fcntl.LOCK_NB):
            shutil.rmtree(CACHE / f"{name}-{key}", ignore_errors=True)
            for left in CACHE.glob(f".building-{name}-{key}-*"):
                shutil.rmtree(left, ignore_errors=True)


@contextlib.contextmanager
def cached(name: str, key: str, build: Callable[[Path], None]) -> Iterator[Path]:
    """The entry `name`-`key`, made by `build(folder)` if it is not there yet; held (no other
    process prunes it) until the block ends."""
    CACHE.mkdir(parents=True, exist_ok=True)
    entry = CACHE / f"{name}-{key}"
    lock = CACHE / f"{name}-{key}.lock"
    with _flock(lock, fcntl.LOCK_SH) as held:
        if not entry.is_dir():
            fcntl.flock(held, fcntl.LOCK_EX)  # the shared lock is let go first: no deadlock
            if not entry.is_dir():  # another process may have built it meanwhile
                for left in CACHE.glob(f".building-{name}-{key}-*"):  # a killed build's
                    shutil.rmtree(left)
                building = CACHE / f".building-{name}-{key}-{uuid.uuid4().hex[:8]}"
                building.mkdir()
                start = time.perf_counter()
                try:
                    build(building)
                except BaseException:
                    shutil.rmtree(building, ignore_errors=True)
                    raise
                os.rename(building, entry)
                print(f"\ntest data {entry.name} built in {time.perf_counter() - start:.0f} s")
                _prune(name, key)
            fcntl.flock(held, fcntl.LOCK_SH)
        yield entry


def build_dataset(folder: Path) -> None:
    """Generate mechanisms and curate paths into `folder`, in this process: the rows of
    `links generate` and `links curate` with the same plan (tests/support/local_dataset.py)."""
    from links_ray.data.generation import GenerationPlan
    from tests.support.local_dataset import generate_and_curate

    plan = GenerationPlan(
        seed=GENERATION["seed"],
        mechanisms=GENERATION["mechanisms"],
        topologies_per_shard=GENERATION["topologies_per_shard"],
        tables=tuple(GENERATION["tables"]),
    )
    generate_and_curate(str(folder), plan, curation_tables=tuple(GENERATION["curation_tables"]))


def build_indexes(dataset: Path) -> Callable[[Path], None]:
    """A builder of `dataset` with its index saved whole and split in each of SPLITS."""

    def build(folder: Path) -> None:
        from links_ray.search.index import RetrievalIndex

        shutil.rmtree(folder)
        link_tree(dataset, folder)
        for parts in SPLITS:
            for part in range(parts):
                RetrievalIndex.open(str(folder), part=part, parts=parts)

    return build


def data_key() -> str:
    """The key of the dataset: the code that generates and curates it, and its parameters."""
    return code_key(("engine", "data"), GENERATION)


def index_key() -> str:
    """The key of the dataset with its indexes saved: the dataset's, and the search's code."""
    return code_key(("engine", "data", "search"), {**GENERATION, "splits": SPLITS})


def scale_dataset(target: Path) -> None:
    """The large dataset, its indexes saved, linked at `target` (a folder of the caller's own:
    what it writes there never reaches the cache)."""
    with cached("dataset", data_key(), build_dataset) as dataset:
        with cached("indexed", index_key(), build_indexes(dataset)) as indexed:
            link_tree(indexed, target)


def cached_json(name: str, key: str, make: Callable[[], object]) -> object:
    """`make()`'s JSON value, made once for `key` and cached as the entry `name`-`key`."""

    def build(folder: Path) -> None:
        (folder / "value.json").write_text(json.dumps(make()))

    with cached(name, key, build) as entry:
        return json.loads((entry / "value.json").read_text())
