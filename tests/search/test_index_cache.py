"""The retrieval index's cache: rebuilt when damaged or when curation changes, and built once
when several processes (Serve replicas) open one root at the same time."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pyarrow.fs as pafs
import pytest

import links_ray
from links_ray.data.commit import committed_shards, marker_file
from links_ray.data.lease import Lease, LeaseHeld
from links_ray.data.store import Store
from links_ray.search.cache import INDEX_FOLDER, cache_folder
from links_ray.search.index import RetrievalIndex

QUERY = np.column_stack([np.cos(np.linspace(0, 6, 50)), np.sin(np.linspace(0, 3, 50))])


@pytest.fixture
def root(dataset: str, tmp_path: Path) -> Path:
    """A private copy of the Serve tests' curated dataset, without its index cache."""
    copy = tmp_path / "data"
    shutil.copytree(dataset, copy)
    shutil.rmtree(copy / INDEX_FOLDER, ignore_errors=True)
    return copy


def forget_saved(root: Path) -> None:
    shutil.rmtree(root / INDEX_FOLDER)


def answers(index: RetrievalIndex) -> list[tuple[int, float]]:
    return [(r["path_id"], round(r["chamfer"], 9)) for r in index.retrieve(QUERY, k=5)]


def test_a_damaged_cache_is_rebuilt(root: Path) -> None:
    built = RetrievalIndex.open(str(root))
    assert built.build_s > 0
    folder = root / cache_folder(0, 1)
    for damaged in ("current.json", "sketches.npy", "bank_positions.npy", "centroids.npy"):
        current = json.loads((folder / "current.json").read_text())
        target = folder / (
            damaged if damaged.endswith(".json") else f"{current['build']}/{damaged}"
        )
        for damage in (target.read_bytes()[:100], b"not what it was at all"):
            target.write_bytes(damage)
            rebuilt = RetrievalIndex.open(str(root))
            assert rebuilt.build_s > 0 and answers(rebuilt) == answers(built), damaged
            assert RetrievalIndex.open(str(root)).build_s == 0  # and saved whole again
            current = json.loads((folder / "current.json").read_text())
            target = folder / (
                damaged if damaged.endswith(".json") else f"{current['build']}/{damaged}"
            )
    # One build is kept: older ones are deleted once a new one is saved.
    assert [p.name for p in folder.iterdir() if p.is_dir()] == [current["build"]]


def test_the_cache_follows_curation(root: Path) -> None:
    full = RetrievalIndex.open(str(root))
    store = Store.open(str(root))
    last = max(committed_shards(store, "curation"))
    marker = root / marker_file(last, "curation")
    saved = marker.read_bytes()
    marker.unlink()  # as if that shard were not curated yet
    fewer = RetrievalIndex.open(str(root))
    assert fewer.build_s > 0 and len(fewer) < len(full)
    assert not set(fewer.path_id.tolist()) - set(full.path_id.tolist())
    marker.write_bytes(saved)  # curated now: the cache of fewer paths no longer serves
    again = RetrievalIndex.open(str(root))
    assert again.build_s > 0 and len(again) == len(full)
    assert answers(again) == answers(full)


OPENER = textwrap.dedent(
    """
    import json, sys
    from links_ray.search.index import RetrievalIndex

    index = RetrievalIndex.open(sys.argv[1])
    print(json.dumps({"paths": len(index), "built": index.build_s > 0}), flush=True)
    """
)


def start_openers(root: Path, count: int) -> list[subprocess.Popen[str]]:
    env = {**os.environ, "PYTHONPATH": str(Path(links_ray.__file__).parents[1])}
    return [
        subprocess.Popen(
            [sys.executable, "-c", OPENER, str(root)], stdout=subprocess.PIPE, text=True, env=env
        )
        for _ in range(count)
    ]


def save_as_a_builder_would(built: Path, root: Path) -> None:
    """Put a saved index back in `root`: its build folder first, `current.json` (the commit)
    last, as `RetrievalIndex.open` saves one."""
    folder = root / cache_folder(0, 1)
    shutil.copytree(built, folder, ignore=shutil.ignore_patterns("current.json"))
    shutil.copy(built / "current.json", folder / "current.json")


def test_processes_opening_one_root_build_the_cache_once(root: Path, tmp_path: Path) -> None:
    store = Store.open(str(root))
    paths = len(RetrievalIndex.open(str(root), rebuild=True))
    built = tmp_path / "built"
    shutil.move(root / cache_folder(0, 1), built)
    forget_saved(root)
    # Another process is building: the openers wait for its cache instead of building too.
    builder = Lease.acquire(store, "index", "a replica building the index")
    openers = start_openers(root, 2)
    time.sleep(8)  # long enough for both to have read the data and found no cache
    assert [opener.poll() for opener in openers] == [None, None]
    save_as_a_builder_would(built, root)  # the builder saves its cache...
    builder.release()  # ...and is done
    results = [json.loads(opener.communicate(timeout=120)[0]) for opener in openers]
    assert results == [{"paths": paths, "built": False}] * 2

    # A builder that gives up without a cache: exactly one of the waiting processes builds.
    forget_saved(root)
    builder = Lease.acquire(store, "index", "a replica that will fail")
    openers = start_openers(root, 2)
    time.sleep(8)
    builder.release()
    results = [json.loads(opener.communicate(timeout=120)[0]) for opener in openers]
    assert sorted(r["built"] for r in results) == [False, True]
    assert {r["paths"] for r in results} == {paths}


HOLDER = textwrap.dedent(
    """
    import sys
    from links_ray.data.lease import Lease, LeaseHeld
    from links_ray.data.store import Store

    with Lease.acquire(Store.open(sys.argv[1]), "index", "a replica building the index"):
        print("held", flush=True)
        sys.stdin.readline()  # until told to finish
    """
)


@pytest.mark.parametrize("where", ["local", "s3"])
def test_opening_waits_a_bounded_time_for_another_builder_and_names_it(
    root: Path, where: str, request: pytest.FixtureRequest
) -> None:
    """A process building the index holds its lease: opening waits for it `wait_s` seconds,
    then fails naming it; a rebuild takes the lease too, so it waits as well."""
    uri = str(root)
    if where == "s3":
        uri = f"{request.getfixturevalue('s3_env')}/data"
        pafs.copy_files(str(root), uri)
    current = f"{cache_folder(0, 1)}/current.json"
    env = {**os.environ, "PYTHONPATH": str(Path(links_ray.__file__).parents[1])}
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER, uri],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        for rebuild in (False, True):
            with pytest.raises(LeaseHeld) as refused:
                RetrievalIndex.open(uri, rebuild=rebuild, wait_s=3)
            message = str(refused.value)
            assert "\n" not in message
            assert message.startswith(
                f"{uri}: gave up on the index lease after waiting 3 s (wait_s=3): it is held by "
                f"a replica building the index (pid {holder.pid} on {socket.gethostname()}, since "
            ), (rebuild, message)
        assert Store.open(uri).read_json(current) is None  # nothing built beside the holder
    finally:
        holder.communicate("done\n", timeout=60)
    assert holder.returncode == 0
    # Its holder done, a rebuild takes the lease and builds.
    assert RetrievalIndex.open(uri, rebuild=True, wait_s=3).build_s > 0
    assert Store.open(uri).read_json(current) is not None
    assert RetrievalIndex.open(uri).build_s == 0
    with pytest.raises(ValueError, match="wait_s must be zero or more, got -1"):
        RetrievalIndex.open(uri, wait_s=-1)
