"""`links import-release` on Ray (`links_ray.cluster.release_import`): the rows of the import in
one process, bit for bit, whatever the workers, a killed actor or a resumed run; its progress
line; and the lean root (`--store ids`), whose derived curated rows are a full import's."""

from __future__ import annotations

import functools
import json
import os
import signal
import threading
from pathlib import Path

import pyarrow as pa
import pytest

import links_ray
from links_ray.cluster.release_import import import_on_ray
from links_ray.data.commit import committed_files, committed_shards
from links_ray.data.derived import derived_tables, has_points
from links_ray.data.lease import Lease
from links_ray.data.store import META, Store, StoreError
from links_ray.release.ids import SHARDS_PER_BATCH
from links_ray.release.import_shards import ImportOptions
from links_ray.release.importer import ReleaseParts, import_release
from links_ray.release.pickles import release_files
from tests.release.test_release_import import BATCHES, CURATED, read_table
from tests.support.cli import links
from tests.support.held_import import held_work, wait_for_pid
from tests.support.release_files import write_release

TABLES = ("mechanisms", "negatives", "paths", "curated")
#: Summary counts an import on Ray must share with the one in one process.
COUNTS = (
    "mechanisms",
    "negatives",
    "topologies",
    "agreeing",
    "disagreeing",
    "locking_at_release_angles",
    "unchecked",
    "worst_error",
    "paths",
    "curated",
    "arcs",
    "circles",
    "both",
    "release_curated_unmatched",
    "release_batches",
    "shards",
)


@pytest.fixture(scope="module")
def release(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("release")
    write_release(folder, BATCHES, curated=CURATED)
    return folder


@pytest.fixture(scope="module")
def one_process(release: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[str, dict]:
    """The import in one process, without Ray: the rows every other import must give."""
    root = str(tmp_path_factory.mktemp("one-process") / "root")
    return root, import_release(str(release), root)


def on_ray(workers: int, progress: bool = False) -> functools.partial:
    return functools.partial(import_on_ray, workers=workers, progress=progress)


def assert_same_import(root: str, reference: tuple[str, dict], summary: dict) -> None:
    for table in TABLES:
        assert read_table(root, table) == read_table(reference[0], table), table
    assert {k: summary[k] for k in COUNTS} == {k: reference[1][k] for k in COUNTS}
    assert not list(Path(root).rglob("_shard-*"))  # no attempt's hidden file left


def test_an_import_on_ray_commits_the_rows_of_one_process(
    ray_cluster: str,
    release: Path,
    one_process: tuple[str, dict],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    root = str(tmp_path / "root")
    summary = import_release(str(release), root, runner=on_ray(workers=2, progress=True))
    assert_same_import(root, one_process, summary)
    assert 1 <= summary["workers"] <= 2 and one_process[1]["workers"] == 1
    # The progress line, in a log: the release's mechanisms, valid or not, all of them.
    lines = capsys.readouterr().err.splitlines()
    total = sum(len(batch) for batch in BATCHES)
    assert lines and lines[-1].startswith(f"{total}/{total} mechanisms (100%), ")
    # Run again, it has nothing left: it commits nothing and starts no actor.
    files = sorted(Path(root).rglob("*.parquet"))
    again = import_release(str(release), root, runner=on_ray(workers=2))
    assert sorted(Path(root).rglob("*.parquet")) == files
    assert again["workers"] == 0 and again["imported_this_run"] == 0


def test_a_killed_actor_s_shard_is_redone_with_the_same_rows(
    ray_cluster: str, release: Path, one_process: tuple[str, dict], tmp_path: Path
) -> None:
    """The actor importing batch 1's first shard is killed in the middle of it (SIGKILL, as a
    lost node): the shard is imported again by another actor, and committed once."""
    root = str(tmp_path / "root")
    hold = SHARDS_PER_BATCH * 1 + 6  # batch 1's mechanisms of 6 joints
    pid_file = tmp_path / "held.pid"
    work = functools.partial(held_work, options=ImportOptions(), hold=hold, pid_file=str(pid_file))
    killed: list[int] = []

    def kill_the_held_actor() -> None:
        pid = wait_for_pid(pid_file)
        os.kill(pid, signal.SIGKILL)
        killed.append(pid)

    killer = threading.Thread(target=kill_the_held_actor)
    killer.start()
    store = Store.open(root)
    source = Store.open(str(release), writable=False)
    with Lease.acquire(store, "writer", "links import-release") as lease:
        # The driver of `import_release`, with the held work in place of the import's own.
        parts = ReleaseParts(source, release_files(source), {}, {})
        done, _ = import_on_ray(store, lease, parts, work, workers=2, progress=False)
    killer.join()
    assert killed, "the held actor was killed"
    assert hold in committed_shards(Store.open(root, writable=False), "curation")
    assert len(done) == one_process[1]["shards"]
    # The import finishes its records (run.json, summaries) with nothing left to commit.
    summary = import_release(str(release), root)
    assert summary["imported_this_run"] == 0
    assert_same_import(root, one_process, summary)


def test_an_interrupted_import_is_finished_on_ray_with_the_same_rows(
    ray_cluster: str, release: Path, one_process: tuple[str, dict], tmp_path: Path
) -> None:
    root = str(tmp_path / "root")

    def stop(step: str) -> None:
        if step == "batch 0 committed":
            raise RuntimeError("stopped")

    with pytest.raises(RuntimeError, match="stopped"):
        import_release(str(release), root, failpoint=stop)
    before = committed_shards(Store.open(root, writable=False), "curation")
    assert 0 < len(before) < one_process[1]["shards"]
    summary = import_release(str(release), root, runner=on_ray(workers=2))
    assert_same_import(root, one_process, summary)
    assert summary["imported_this_run"] == one_process[1]["mechanisms"] - sum(
        marker["stats"]["mechanisms"] for marker in before.values()
    )


def test_a_lean_import_derives_the_curated_rows_of_a_full_one(
    ray_cluster: str, release: Path, one_process: tuple[str, dict], tmp_path: Path
) -> None:
    """`--store ids`: mechanisms, and curated as ids without points, as `links generate
    --tables mechanisms` then `links curate --store ids` leave a root; its readers derive the
    curated points, which are the full import's stored ones, bit for bit."""
    root = str(tmp_path / "lean")
    command = ["import-release", str(release), "--out", root, "--store", "ids"]
    done = links(*command, "--workers", "2", "--address", ray_cluster, "--json")
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["tables"] == ["mechanisms", "curated"] and summary["path_store"] == "ids"
    store = Store.open(root, writable=False)
    assert [t for t in TABLES if committed_files(store, t)] == ["mechanisms", "curated"]
    assert not has_points(store.read_parquet(committed_files(store, "curated")[0]).schema)
    assert store.read_json(f"{META}/run.json")["tables"] == ["mechanisms"]
    curation = store.read_json(f"{META}/curation.json")
    assert curation["tables"] == ["curated"] and curation["path_store"] == "ids"
    assert derived_tables(store) == ("simulations", "paths", "curated")
    assert read_table(root, "mechanisms") == read_table(one_process[0], "mechanisms")

    def rows(at: str) -> pa.Table:
        return links_ray.load(at, "curated", format="arrow").sort_by("path_id")

    lean, full = rows(root), rows(one_process[0])
    assert lean.num_rows == one_process[1]["curated"] > 0
    assert lean.select(full.column_names).equals(full)
    # Resumed with other tables, it is refused.
    with pytest.raises(StoreError, match="holds another run"):
        import_release(str(release), root)


@pytest.mark.parametrize(
    ("tables", "store", "message"),
    [
        ("mechanisms,simulations", "points", "tables must be among mechanisms, negatives"),
        ("paths,curated", "points", "tables must include mechanisms"),
        ("mechanisms,negatives", "points", "tables must include paths or curated"),
        ("mechanisms,curated", "bits", "store must be one of points, ids"),
    ],
)
def test_bad_tables_are_refused_in_one_line(
    release: Path, tmp_path: Path, tables: str, store: str, message: str
) -> None:
    root = tmp_path / "root"
    with pytest.raises(ValueError, match=message) as refused:
        import_release(str(release), str(root), tables=tables, path_store=store)
    assert "\n" not in str(refused.value)
    assert not root.exists() or not list(root.rglob("*.parquet"))
