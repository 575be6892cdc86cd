"""The generation service end to end on a real local Ray cluster and real Parquet files.

Every row is re-checked against the engine: the dataset rules, a fresh simulation, and the
negatives' locks. Faults (a killed actor, a killed driver) must leave exactly the rows of an
undisturbed run.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.dataset as pads
import pytest

import links_ray
from links_ray.cluster import generation
from links_ray.cluster.curation import curate
from links_ray.cluster.generation import generate
from links_ray.data.commit import committed_files, committed_shards, marker_file
from links_ray.data.generation import NEGATIVE_ID_BASE, GenerationPlan
from links_ray.data.schemas import GENERATION_TABLES as TABLES
from links_ray.data.store import META, Store, StoreError
from links_ray.engine.kinematics.mechanism import analyze_topology, dataset_rule_violations
from tests.support.local_dataset import generate_and_curate
from tests.support.needs import missing


def read_table(store: Store, table: str) -> pa.Table:
    """A plain pyarrow dataset read of one table, sorted by id."""
    dataset = pads.dataset(store.path(table), filesystem=store.fs, partitioning="hive")
    return dataset.to_table().sort_by("mechanism_id")


def assert_only_committed_files(uri: str, tables: tuple[str, ...] = TABLES) -> None:
    """Each table's folder holds exactly the files that markers name, hidden ones included:
    a plain read sees exactly the committed rows, as `load` does."""
    store = Store.open(uri, writable=False)
    for table in tables:
        files = sorted(committed_files(store, table))
        assert files and store.list_files(table) == files, table


def read_all(uri: str) -> dict[str, pa.Table]:
    store = Store.open(uri)
    return {table: read_table(store, table) for table in TABLES}


def check_dataset(uri: str, mechanisms: int) -> dict[str, pa.Table]:
    """Assert every rule of docs/reference/contract.md on the dataset at `uri`; return tables."""
    tables = read_all(uri)
    rows = tables["mechanisms"].to_pylist()
    assert [row["mechanism_id"] for row in rows] == list(range(mechanisms))
    simulations = tables["simulations"].to_pylist()
    assert [row["mechanism_id"] for row in simulations] == list(range(mechanisms))
    assert mechanisms > 0
    variants: dict[int, list[bytes]] = {}
    for row, simulation in zip(rows, simulations, strict=True):
        n = row["n_joints"]
        assert 8 <= n <= 20 and row["mechanism_id"] == 5 * row["topology_id"] + row["variant"]
        adjacency = np.array(row["adjacency"], dtype=np.uint8).reshape(n, n)
        node_types = np.array(row["node_types"])
        positions = np.array(row["positions"]).reshape(n, 2)
        topology = analyze_topology(adjacency, node_types)
        assert dataset_rule_violations(topology, positions) == []
        fresh = links_ray.simulate(adjacency, node_types, positions)  # raises if it locks
        stored = np.array(simulation["trajectories"], dtype=np.float32).reshape(n, 200, 2)
        np.testing.assert_allclose(stored, fresh, atol=2e-6)
        variants.setdefault(row["topology_id"], []).append(positions.tobytes())
    # A topology's variants are distinct position sets.
    assert sum(map(len, variants.values())) == mechanisms
    assert all(len(set(v)) == len(v) for v in variants.values())
    negatives = tables["negatives"].to_pylist()
    assert negatives, "the run met locking candidates"
    for row in negatives[:200]:
        n = row["n_joints"]
        assert row["mechanism_id"] >= NEGATIVE_ID_BASE
        positions = np.array(row["positions"]).reshape(n, 2)
        with pytest.raises(links_ray.LockingError) as lock:
            links_ray.simulate(
                np.array(row["adjacency"]).reshape(n, n), row["node_types"], positions
            )
        assert (lock.value.step, lock.value.node) == (row["locked_step"], row["locked_node"])
    summary = Store.open(uri).read_json(f"{META}/summary.json")
    assert summary["complete"] and summary["rows"]["mechanisms"] == mechanisms
    assert summary["rows"]["negatives"] == len(negatives)
    return tables


def assert_same_rows(a: dict[str, pa.Table], b: dict[str, pa.Table]) -> None:
    for table in TABLES:
        left = a[table].select(sorted(a[table].column_names))
        right = b[table].select(sorted(b[table].column_names))
        assert left.equals(right), f"{table} differs"


#: The plan of the reference run and of every run compared with it.
PLAN = GenerationPlan(seed=3, mechanisms=137, topologies_per_shard=2)


@pytest.fixture(scope="module")
def reference_run(ray_cluster: str, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """An undisturbed run: 137 mechanisms, seed 3, small shards so there are many of them."""
    out = str(tmp_path_factory.mktemp("reference") / "data")
    summary = generate(out, 137, seed=3, workers=2, progress=False, topologies_per_shard=2)
    return {"out": out, "summary": summary, "tables": check_dataset(out, 137)}


def test_local_run_is_complete_and_valid(reference_run: dict) -> None:
    summary = reference_run["summary"]
    assert summary["rows"]["mechanisms"] == summary["rows"]["simulations"] == 137
    assert summary["shards"] == len(committed_shards(Store.open(reference_run["out"])))
    assert set(summary["by_joint_count"]) == {str(n) for n in range(8, 21)}
    assert summary["valid_per_core_second"] > 0
    # Nothing is left behind once a run completes: no hidden file, no uncommitted one.
    assert_only_committed_files(reference_run["out"])


def test_same_rows_whatever_the_workers_or_shards(
    ray_cluster: str, tmp_path: Path, reference_run: dict
) -> None:
    out = str(tmp_path / "one-worker")
    generate(out, 137, seed=3, workers=1, progress=False, topologies_per_shard=5)
    assert_same_rows(read_all(out), reference_run["tables"])


def test_a_run_beside_other_work_takes_the_cpu_left(
    ray_cluster: str, tmp_path: Path, reference_run: dict
) -> None:
    """With one of the cluster's two CPUs held by other work for the whole run (a Serve
    replica, another job's actor), a run asking for two workers finishes on the CPU left, with
    the reference's rows: no shard waits on an actor that waits for a CPU."""
    import ray

    from tests.support.serve_app import stop_shared_app

    stop_shared_app()  # the CPUs are this test's to hold

    @ray.remote(num_cpus=1)
    class OtherWork:
        def ready(self) -> None:
            return None

    other = OtherWork.remote()
    ray.get(other.ready.remote(), timeout=300)
    out = str(tmp_path / "beside")
    finished: dict = {}
    run = threading.Thread(
        target=lambda: finished.update(
            generate(out, 137, seed=3, workers=2, progress=False, topologies_per_shard=2)
        ),
        daemon=True,
    )
    try:
        run.start()
        run.join(timeout=600)
        assert not run.is_alive(), "the run waited on an actor that has no CPU"
    finally:
        ray.kill(other)
        run.join(timeout=600)
    assert finished["complete"] and finished["workers"] == 1, finished
    assert_same_rows(read_all(out), reference_run["tables"])


def test_rerun_keeps_committed_shards(
    ray_cluster: str, reference_run: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A finished run asked again changes nothing and starts no Ray: it says so, with the
    saved summary."""
    store = Store.open(reference_run["out"])
    before = {
        f: store.fs.get_file_info(store.path(f)).mtime for f in store.list_files("mechanisms")
    }

    def no_ray(address: object = None) -> None:
        raise AssertionError("a finished run started Ray")

    monkeypatch.setattr(generation, "connect", no_ray)
    summary = generate(reference_run["out"], 137, seed=3, progress=False, topologies_per_shard=2)
    after = {f: store.fs.get_file_info(store.path(f)).mtime for f in store.list_files("mechanisms")}
    assert before == after and summary["complete"] and summary["nothing_to_do"]
    assert summary["rows"] == reference_run["summary"]["rows"]


def test_another_run_in_the_same_place_is_refused(reference_run: dict) -> None:
    with pytest.raises(StoreError, match=r"holds another run.*seed=3"):
        generate(reference_run["out"], 137, seed=4, progress=False, topologies_per_shard=2)


def test_a_root_is_extended_in_place_to_the_rows_of_a_fresh_run(
    ray_cluster: str, tmp_path: Path, reference_run: dict
) -> None:
    """More mechanisms asked of a finished root extend its plan: its files stay as they
    were, the new shards add the rest, and the rows are those of a fresh run of the larger
    size (written here without Ray, as each generator actor writes its shards)."""
    root = tmp_path / "extended"
    shutil.copytree(reference_run["out"], root)
    before = {p: p.read_bytes() for p in root.rglob("*.parquet")}
    summary = generate(str(root), 200, seed=3, progress=False, topologies_per_shard=2)
    assert summary["complete"] and summary["rows"]["mechanisms"] == 200
    assert summary["plan"]["extended_from"] == [137]
    # Its rate is of the rows it made: the 137 it found took none of its seconds.
    assert summary["mechanisms_this_run"] == 200 - 137
    assert summary["mechanisms_per_second"] == pytest.approx(63 / summary["seconds"])
    assert all(path.read_bytes() == data for path, data in before.items())
    fresh = GenerationPlan(seed=3, mechanisms=200, topologies_per_shard=2)
    generate_and_curate(str(tmp_path / "fresh"), fresh)
    assert_same_rows(read_all(str(root)), read_all(str(tmp_path / "fresh")))
    # Fewer mechanisms than the root holds: refused in one line, the root untouched.
    command = reference_command(str(root), ray_cluster)
    refused = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert refused.returncode == 2
    assert refused.stderr == (
        f"links generate: error: {root}: the root holds 200 mechanisms: a root is extended, it "
        "never shrinks (asked for 137); use a new root for fewer\n"
    )
    assert json.loads((root / META / "run.json").read_text())["mechanisms"] == 200


def test_bad_out_is_a_clear_error(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    with pytest.raises(StoreError, match="cannot use"):
        generate(str(blocker / "data"), 10, progress=False)
    with pytest.raises(StoreError, match="unsupported scheme"):
        generate("ftp://example/data", 10, progress=False)
    with pytest.raises(ValueError, match="mechanisms"):
        generate(str(tmp_path / "x"), 0, progress=False)


def test_left_out_tables_change_no_row_of_the_written_ones(
    ray_cluster: str, tmp_path: Path, reference_run: dict
) -> None:
    """`tables` in any order: the chosen tables' rows are the full run's, the markers and the
    summary name only them, and run.json records them."""
    out = str(tmp_path / "no-simulations")
    summary = generate(
        out, 137, seed=3, progress=False, topologies_per_shard=2, tables="negatives,mechanisms"
    )
    store = Store.open(out)
    assert store.list_files("simulations") == []
    for table in ("mechanisms", "negatives"):
        left, right = read_table(store, table), reference_run["tables"][table]
        assert left.select(sorted(left.column_names)).equals(
            right.select(sorted(right.column_names))
        ), f"{table} differs"
    markers = committed_shards(store)
    assert len(markers) == reference_run["summary"]["shards"]
    assert {table for marker in markers.values() for table in marker["files"]} == {
        "mechanisms",
        "negatives",
    }
    assert summary["complete"] and summary["plan"]["tables"] == ["mechanisms", "negatives"]
    assert summary["rows"] == {
        table: reference_run["summary"]["rows"][table] for table in ("mechanisms", "negatives")
    }
    assert store.read_json(f"{META}/run.json")["tables"] == ["mechanisms", "negatives"]


def test_resuming_with_other_tables_is_refused_in_one_line(
    ray_cluster: str, tmp_path: Path, reference_run: dict
) -> None:
    with pytest.raises(StoreError, match=r"holds another run \(tables=mechanisms,simulations,"):
        generate(
            reference_run["out"],
            137,
            seed=3,
            progress=False,
            topologies_per_shard=2,
            tables="mechanisms",
        )
    command = [*reference_command(reference_run["out"], ray_cluster), "--tables", "mechanisms"]
    refused = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert refused.returncode == 2
    assert refused.stderr == (
        f"links generate: error: {reference_run['out']} holds another run "
        "(tables=mechanisms,simulations,negatives); use a new root or the same options\n"
    )
    # A root recorded before tables could be chosen holds them all: the same plan resumes.
    legacy = tmp_path / "legacy"
    shutil.copytree(reference_run["out"], legacy)
    run = json.loads((legacy / META / "run.json").read_text())
    del run["tables"]
    (legacy / META / "run.json").write_text(json.dumps(run))
    again = generate(str(legacy), 137, seed=3, progress=False, topologies_per_shard=2)
    assert again["complete"] and again["rows"] == reference_run["summary"]["rows"]


@pytest.mark.parametrize(
    ("tables", "message"),
    [
        ("simulations", "tables must include mechanisms, got simulations"),
        (
            "mechanisms,paths",
            "tables must be among mechanisms, simulations, negatives, got 'paths'",
        ),
        ("", "tables must be among mechanisms, simulations, negatives, got ''"),
    ],
)
def test_bad_tables_are_refused_in_one_line(tmp_path: Path, tables: str, message: str) -> None:
    with pytest.raises(ValueError, match=f"^{message}$"):
        generate(str(tmp_path / "data"), 10, progress=False, tables=tables)
    command = [sys.executable, "-m", "links_ray.cli", "generate", "--out", str(tmp_path / "data")]
    refused = subprocess.run(
        [*command, "--mechanisms", "10", "--tables", tables],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert (refused.returncode, refused.stderr) == (2, f"links generate: error: {message}\n")
    assert not (tmp_path / "data").exists()


class PollingReader:
    """Reads a root over and over while a run writes it, as a user's notebook might.

    Each poll loads `mechanisms` then `simulations` (two separate `load` calls) and then reads
    the commit markers. Every row it saw must belong to a shard committed by then, every shard
    must be whole, and every shard of the first read must be in the second: a reader never sees
    mechanisms without their simulations.
    """

    def __init__(self, uri: str, plan: GenerationPlan) -> None:
        self.uri = uri
        self.shard_of = {t: s.shard_id for s in plan.shards() for t in s.topology_ids()}
        self.polls = 0
        self.problems: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run)

    def __enter__(self) -> PollingReader:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join()

    def _rows_per_shard(self, table: str) -> dict[int, int]:
        """Rows per shard in one `load` of `table` (empty while it has no committed rows)."""
        try:
            ids = links_ray.load(self.uri, table, columns=["mechanism_id"], format="arrow")
        except ValueError:  # no committed rows yet, or no root yet
            return {}
        shards = [self.shard_of[i // 5] for i in ids.column("mechanism_id").to_pylist()]
        return dict(Counter(shards))

    def _run(self) -> None:
        while not self._stop.is_set():
            mechanisms = self._rows_per_shard("mechanisms")
            simulations = self._rows_per_shard("simulations")
            if not mechanisms:
                time.sleep(0.01)
                continue
            markers = committed_shards(Store.open(self.uri, writable=False))
            self.polls += 1
            for table, seen in (("mechanisms", mechanisms), ("simulations", simulations)):
                for shard, count in seen.items():
                    if shard not in markers:
                        self.problems.append(f"{table}: rows of uncommitted shard {shard}")
                    elif count != markers[shard]["rows"][table]:
                        self.problems.append(f"{table}: {count} rows of shard {shard}")
            if set(mechanisms) - set(simulations):
                missing = sorted(set(mechanisms) - set(simulations))
                self.problems.append(f"mechanisms of shards {missing} without simulations")


def generator_pids() -> list[int]:
    """PIDs of live generator actors (Ray titles their processes `ray::GeneratorActor`)."""
    pids = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if cmdline.read_bytes().startswith(b"ray::GeneratorActor"):
                pids.append(int(cmdline.parent.name))
        except OSError:  # the process ended while we looked
            pass
    return pids


def test_killed_actor_shard_is_redone(
    ray_cluster: str, tmp_path: Path, reference_run: dict
) -> None:
    out = str(tmp_path / "killed-actor")
    store = Store.open(out)
    killed: list[int] = []

    def kill_one_actor_mid_run() -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not killed:
            shards = store.list_files(f"{META}/shards")
            pids = generator_pids()
            if shards and pids:
                os.kill(pids[0], signal.SIGKILL)
                killed.append(len(shards))
            time.sleep(0.05)

    killer = threading.Thread(target=kill_one_actor_mid_run)
    killer.start()
    with PollingReader(out, PLAN) as reader:
        generate(out, 137, seed=3, workers=2, progress=False, topologies_per_shard=2)
    killer.join()
    assert killed and killed[0] < reference_run["summary"]["shards"], "killed mid-run"
    assert_same_rows(read_all(out), reference_run["tables"])
    assert_only_committed_files(out)
    assert reader.polls > 0 and reader.problems == []


def reference_command(out: str, address: str) -> list[str]:
    """`links generate` of the reference run's plan into `out`, on the cluster at `address`."""
    plan = ["--mechanisms", "137", "--seed", "3", "--shard-topologies", "2"]
    return [
        sys.executable,
        "-m",
        "links_ray.cli",
        "generate",
        "--out",
        out,
        *plan,
        "--address",
        address,
    ]


def test_killed_driver_run_is_finished_by_the_same_command(
    ray_cluster: str, tmp_path: Path, reference_run: dict
) -> None:
    out = str(tmp_path / "killed-driver")
    command = reference_command(out, ray_cluster)
    env = {**os.environ, "RAY_AUTH_MODE": "disabled"}
    store = Store.open(out)
    with PollingReader(out, PLAN) as reader:
        driver = subprocess.Popen(
            command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not store.list_files(f"{META}/shards"):
            time.sleep(0.05)
        # A second driver on the same root, or a curation, is refused in one line naming the
        # driver that holds it (stopped meanwhile, so that it cannot finish first).
        driver.send_signal(signal.SIGSTOP)
        for second in (command, [*command[:3], "curate", out, "--address", ray_cluster]):
            refused = subprocess.run(second, env=env, capture_output=True, text=True, timeout=300)
            assert refused.returncode != 0
            assert refused.stderr.count("\n") == 1, refused.stderr
            assert f"in use by links generate (pid {driver.pid} on" in refused.stderr
        driver.send_signal(signal.SIGKILL)
        driver.wait()
        partial = len(store.list_files(f"{META}/shards"))
        total = reference_run["summary"]["shards"]
        assert 0 < partial < total, "the driver died mid-run"
        # Its lease dies with it (same host): the same command goes on at once.
        rerun = subprocess.run(command, env=env, capture_output=True, text=True, timeout=300)
        assert rerun.returncode == 0, rerun.stderr
    assert_same_rows(read_all(out), reference_run["tables"])
    assert_only_committed_files(out)
    assert reader.polls > 0 and reader.problems == []


def test_an_unreadable_marker_is_redone(
    ray_cluster: str, tmp_path: Path, reference_run: dict
) -> None:
    out = tmp_path / "damaged"
    shutil.copytree(reference_run["out"], out)
    damaged = out / marker_file(3)
    damaged.write_bytes(damaged.read_bytes()[:40])
    store = Store.open(str(out))
    assert 3 not in committed_shards(store)
    summary = generate(str(out), 137, seed=3, progress=False, topologies_per_shard=2)
    assert summary["complete"] and 3 in committed_shards(store)
    assert_same_rows(read_all(str(out)), reference_run["tables"])


def test_s3_run_matches_the_local_one(ray_cluster: str, s3_env: str, reference_run: dict) -> None:
    uri = f"{s3_env}/links/data"
    summary = generate(uri, 137, seed=3, workers=2, progress=False, topologies_per_shard=2)
    assert summary["complete"] and summary["out"] == uri
    assert_same_rows(check_dataset(uri, 137), reference_run["tables"])
    assert_only_committed_files(uri)


def test_s3_bad_credentials_and_unreachable_store_are_clear(
    s3_env: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "not-the-secret")
    with pytest.raises(StoreError, match="credentials") as refused:
        generate(f"{s3_env}/data", 10, progress=False)
    assert "not-the-secret" not in str(refused.value)
    monkeypatch.undo()
    with socket.socket() as closed:
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
    monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{port}")
    start = time.monotonic()
    with pytest.raises(StoreError, match="unreachable"):
        generate(f"{s3_env}/data", 10, progress=False)
    assert time.monotonic() - start < 15


def error_lines(stderr: str, command: str) -> list[str]:
    """The command's own error lines, after checking it printed no traceback.

    Ray's log monitor may still forward a line of the cluster's own (prefixed "(raylet)") as a
    driver disconnects; those are the cluster's, not the command's.
    """
    assert "Traceback" not in stderr, stderr
    return [line for line in stderr.splitlines() if line.startswith(f"links {command}: error: ")]


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 1 MiB tmpfs: the run's data (about 2 MB) cannot fit."""
    mount = tmp_path / "small-disk"
    mount.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)],
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        missing(f"cannot mount a small tmpfs (needs root): {done.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def test_a_full_disk_ends_the_run_in_one_line_and_the_same_command_finishes_it(
    ray_cluster: str, small_disk: Path, reference_run: dict
) -> None:
    out = str(small_disk / "data")
    command = reference_command(out, ray_cluster)
    env = {**os.environ, "RAY_AUTH_MODE": "disabled"}
    full = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert full.returncode == 2, full.stderr
    (last,) = error_lines(full.stderr, "generate")
    assert "No space left on device" in last
    # What is there is whole: committed shards only, each with all its rows in every table.
    store = Store.open(out, writable=False)
    markers = committed_shards(store)
    assert 0 < len(markers) < reference_run["summary"]["shards"]
    for table in ("mechanisms", "simulations"):
        rows = links_ray.load(out, table, format="arrow")
        assert len(rows) == sum(m["rows"][table] for m in markers.values())
    # Space is back: the same command finishes the run, with the rows of an undisturbed one.
    subprocess.run(["mount", "-o", "remount,size=64m", str(small_disk)], check=True)
    again = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr
    assert_same_rows(read_all(out), reference_run["tables"])
    assert not [f for t in TABLES for f in store.list_files(t) if "/_" in f]


def test_a_full_disk_stops_curation_in_one_line_and_the_same_command_finishes_it(
    ray_cluster: str, small_disk: Path, reference_run: dict, tmp_path: Path
) -> None:
    undisturbed = tmp_path / "undisturbed"
    shutil.copytree(reference_run["out"], undisturbed)
    curate(str(undisturbed), progress=False)
    # Room for the generated tables (about 2.1 MB), not for their paths as well.
    subprocess.run(["mount", "-o", "remount,size=3m", str(small_disk)], check=True)
    out = small_disk / "data"
    shutil.copytree(reference_run["out"], out)
    command = [sys.executable, "-m", "links_ray.cli", "curate", str(out), "--address", ray_cluster]
    env = {**os.environ, "RAY_AUTH_MODE": "disabled"}
    full = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert full.returncode == 2, full.stderr
    (last,) = error_lines(full.stderr, "curate")
    assert last.startswith("links curate: error: curation stopped: the store refused shard")
    assert "No space left on device" in last
    store = Store.open(str(out), writable=False)
    markers = committed_shards(store, "curation")
    assert len(markers) < len(committed_shards(store))
    paths = links_ray.load(str(out), "paths", format="arrow") if markers else None
    assert paths is None or len(paths) == sum(m["rows"]["paths"] for m in markers.values())
    subprocess.run(["mount", "-o", "remount,size=64m", str(small_disk)], check=True)
    again = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr
    for table in ("paths", "curated"):
        ours = links_ray.load(str(out), table, format="arrow").sort_by("path_id")
        theirs = links_ray.load(str(undisturbed), table, format="arrow").sort_by("path_id")
        assert ours.equals(theirs), f"{table} differs"


def test_a_root_recorded_with_grown_from_still_reads_and_is_extended(tmp_path: Path) -> None:
    """A root written before the extension's record was named `extended_from` (its run.json
    says `grown_from`) resumes as the plan it recorded, and is extended from it."""
    store = Store.open(str(tmp_path / "old"))
    first = GenerationPlan(seed=3, mechanisms=100, topologies_per_shard=4)
    held = first.extended_to(150)
    record = held.config()
    record["grown_from"] = record.pop("extended_from")
    store.write_json(f"{META}/run.json", record)
    asked = GenerationPlan(seed=3, mechanisms=150, topologies_per_shard=4)
    resumed = generation.plan_on_root(store, asked, generation.RECORD_DEFAULTS)
    assert resumed == held and resumed.extended_from == (100,)
    extended = generation.plan_on_root(
        store,
        GenerationPlan(seed=3, mechanisms=220, topologies_per_shard=4),
        generation.RECORD_DEFAULTS,
    )
    assert extended == held.extended_to(220)
    assert extended.shards()[: len(held.shards())] == held.shards()
    assert store.read_json(f"{META}/run.json")["extended_from"] == [100, 150]
