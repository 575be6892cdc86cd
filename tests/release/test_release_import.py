"""Import of the LINKS release's own files: the restricted unpickler, the import into a root
(bit-for-bit positions, the check against the release's trajectories, negatives, the release's
curated set), its faults (a refused name, a batch cut short, a wrong shape), resume, and the
root in use (stats, retrieval, synthesis, `ray_dataset`, `links serve` and the studio), which
only the import writes to."""

from __future__ import annotations

import json
import os
import pickle
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pytest

from links_ray.data.commit import ShardWriter, committed_files, committed_shards
from links_ray.data.curation import path_table
from links_ray.data.generation import NEGATIVE_ID_BASE
from links_ray.data.lease import Lease, LeaseHeld
from links_ray.data.store import Store, StoreError
from links_ray.engine.kinematics.sampling import PositionSampler
from links_ray.engine.kinematics.solver import TopologySimulator
from links_ray.engine.kinematics.topology import grow_topology
from links_ray.release import import_shards
from links_ray.release.ids import BATCH_STRIDE, SHARDS_PER_BATCH, release_location
from links_ray.release.importer import import_release
from links_ray.release.pickles import ReleaseFileError, read_batches, release_files
from links_ray.serve.app import bindable_port
from tests.support.cli import links
from tests.support.fourbars import stretched_four_bar, window_slack
from tests.support.release_files import as_release, release_simulation, write_release
from tests.support.serving import links_serve
from tests.support.studio_page import draw, open_studio


def mechanisms(seed: int, batches: int, topologies: int) -> list[list[tuple]]:
    """Release batches of links-ray topologies (6 to 10 joints mixed), five variants each; the
    last batch ends with two four-bars that lock in links-ray's turn."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(batches):
        batch = []
        for t in range(topologies):
            topology = grow_topology(rng, 6 + 2 * (t % 3))
            found = PositionSampler(TopologySimulator.from_topology(topology), 200).search(
                5, rng, "sequential"
            )
            for positions in found.positions[:5]:
                batch.append(as_release(topology.adjacency, topology.node_types, positions))
        out.append(batch)
    # Assembles at every angle the release and links-ray sample but locks between links-ray's
    # steps 1 and 2; then one that cannot turn at the release's angles either.
    for step, slack in ((1, window_slack(200)), (50, -1e-4)):
        locked = stretched_four_bar(step, 200, slack)
        out[-1].append(as_release(locked["adjacency"], locked["node_types"], locked["positions"]))
    return out


BATCHES = mechanisms(seed=5, batches=3, topologies=4)
#: The release's curated (j, node) pairs per batch.
CURATED = [[(0, 1), (0, 3), (7, 4)], [(12, 5)], [(3, 2), (19, 1), (9, 7)]]


def place(mechanism_id: int) -> tuple[int, int]:
    """(release batch, release index) of an imported mechanism id."""
    batch, index = release_location(np.array([mechanism_id]))
    return int(batch[0]), int(index[0])


def read_table(root: str, table: str) -> dict:
    """A table's committed rows by mechanism_id (or path_id) as Python values."""
    store = Store.open(root, writable=False)
    rows = {}
    key = "path_id" if table in ("paths", "curated") else "mechanism_id"
    for relative in committed_files(store, table):
        for row in store.read_parquet(relative).to_pylist():
            rows[row[key]] = row
    return rows


@pytest.fixture(scope="module")
def release(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("release")
    write_release(folder, BATCHES, curated=CURATED)
    return folder


@pytest.fixture(scope="module")
def imported(release: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[str, dict]:
    root = str(tmp_path_factory.mktemp("imported") / "root")
    return root, import_release(str(release), root)


# -- the restricted unpickler ------------------------------------------------------------------


class RunsACommand:
    """Unpickling it would run a shell command that creates `marker`."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple:
        return (os.system, (f"touch {self.marker}",))


def test_a_pickle_that_would_run_a_command_is_refused_and_never_runs(
    ray_cluster: str, tmp_path: Path
) -> None:
    release = tmp_path / "release"
    write_release(release, BATCHES[:2])
    marker = tmp_path / "ran"
    with open(release / "dataset", "ab") as out:
        pickle.dump([RunsACommand(marker)], out)
    root = str(tmp_path / "root")
    command = ["import-release", str(release), "--out", root, "--address", ray_cluster]
    result = subprocess.run(
        [sys.executable, "-m", "links_ray.cli", *command], capture_output=True, text=True
    )
    assert result.returncode == 2
    name = f"{os.system.__module__}.system"
    # The import on Ray finishes the batches before it, whose progress lines come first.
    *progress, error = result.stderr.splitlines()
    assert error == (
        f"links import-release: error: {release}/dataset batch 2 names {name}; "
        "only numpy arrays and lists are read"
    )
    strays = [
        line for line in progress if not re.fullmatch(r"[\d,]+/~?[\d,]+ mechanisms \(.*", line)
    ]
    assert not strays, strays
    assert not marker.exists()
    # The batches before it were imported and committed.
    rows = read_table(root, "mechanisms")
    assert {int(b) for b in release_location(np.array(list(rows)))[0]} == {0, 1}


class HugeArray:
    """Unpickling it would ask numpy's reconstructor for a 10 TB array."""

    def __reduce__(self) -> tuple:
        return (np.ndarray.__reduce__(np.zeros(1))[0], (np.ndarray, (10**13,), b"b"))


def test_an_array_larger_than_its_file_is_refused(tmp_path: Path) -> None:
    with open(tmp_path / "dataset", "wb") as out:
        pickle.dump([[np.zeros(3)]], out)
        pickle.dump([HugeArray()], out)
    batches = read_batches(Store.open(str(tmp_path), writable=False), "dataset")
    assert next(batches)[0] == 0
    with pytest.raises(
        ReleaseFileError, match=r"dataset batch 1 at byte \d+ is not a readable pickle"
    ):
        next(batches)


def test_any_protocol_numpy_1_names_and_both_file_names_read_the_same(tmp_path: Path) -> None:
    batch = BATCHES[0][:6]
    reads = []
    generator = {2: "dataset", 3: None, 4: "links_subset", 5: None}
    for protocol in (2, 3, 4, 5):
        folder = tmp_path / f"p{protocol}"
        name = generator[protocol]
        write_release(folder, [batch], generator_name=name, protocol=protocol)
        store = Store.open(str(folder), writable=False)
        files = release_files(store)
        assert files["dataset"] == (name or "dataset")
        assert files["simulation_dataset"] == (
            f"Solutions_{name}" if name else "simulation_dataset"
        )
        reads.append(next(read_batches(store, files["dataset"]))[2])
    numpy1 = tmp_path / "numpy1"
    numpy1.mkdir()
    data = pickle.dumps([list(entry) for entry in batch], protocol=2)
    assert b"numpy._core.multiarray" in data
    (numpy1 / "dataset").write_bytes(data.replace(b"numpy._core.", b"numpy.core."))
    reads.append(next(read_batches(Store.open(str(numpy1), writable=False), "dataset"))[2])
    for read in reads:
        for (a, x0, fixed), expected in zip(read, batch, strict=True):
            for got, want in zip((a, x0, fixed), expected, strict=True):
                assert got.dtype == want.dtype
                np.testing.assert_array_equal(got, want)


def test_both_file_names_at_once_are_refused(tmp_path: Path) -> None:
    write_release(tmp_path, BATCHES[:1])
    (tmp_path / "Solutions_dataset").write_bytes((tmp_path / "simulation_dataset").read_bytes())
    with pytest.raises(ValueError, match="holds both simulation_dataset and Solutions_dataset"):
        import_release(str(tmp_path), str(tmp_path / "root"))


def test_a_batch_cut_short_is_reported_at_its_offset_after_the_ones_before_commit(
    tmp_path: Path,
) -> None:
    release = tmp_path / "release"
    write_release(release, BATCHES)
    data = (release / "dataset").read_bytes()
    offsets = [offset for _, offset, _ in read_batches(Store.open(str(release)), "dataset")]
    (release / "dataset").write_bytes(data[: len(data) - 100])
    root = str(tmp_path / "root")
    with pytest.raises(
        ReleaseFileError, match=f"dataset batch 2 at byte {offsets[2]} is cut short"
    ):
        import_release(str(release), root)
    rows = read_table(root, "mechanisms")
    batches, _ = release_location(np.array(list(rows)))
    assert sorted(set(batches.tolist())) == [0, 1]
    assert len(rows) == len(BATCHES[0]) + len(BATCHES[1])


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        (2, r"batch 1 index 3: x0 must be \(\d+, 2\) float32, got \(\d+, 2\) float64"),
        (1, r"batch 1 index 3: A must be \((\d+), \1\) bool, got \(\d+, \d+\) int64"),
        (0, r"batch 1 index 3: node_type must be \(n,\) bool"),
    ],
)
def test_a_wrong_shape_or_type_names_the_batch_and_index(
    tmp_path: Path, entry: int, message: str
) -> None:
    bad = [list(batch) for batch in BATCHES[:2]]
    a, x0, fixed = bad[1][3]
    bad[1][3] = (
        a.astype(np.int64) if entry == 1 else a,
        x0.astype(np.float64) if entry == 2 else x0,
        fixed[:, None] if entry == 0 else fixed,
    )
    write_release(tmp_path, bad)
    with pytest.raises(ReleaseFileError, match=message):
        import_release(str(tmp_path), str(tmp_path / "root"))


def test_float64_trajectories_as_the_releases_numpy_solver_makes_them_import(
    imported: tuple[str, dict], tmp_path: Path
) -> None:
    """The release's own solver (`sim.solve_rev_vectorized`) builds x_sol with `np.zeros`:
    float64. Such files import to the very rows of the float32 files, positions bit for bit,
    and every trajectory agrees with links-ray's solver as the float32 ones do."""
    folder = tmp_path / "release"
    write_release(folder, BATCHES, curated=CURATED, dtype=np.float64)
    solutions = next(read_batches(Store.open(str(folder), writable=False), "simulation_dataset"))[2]
    assert solutions[0][0].dtype == np.float64
    root = str(tmp_path / "root")
    summary = import_release(str(folder), root)
    _, from_float32 = imported
    for key in ("mechanisms", "negatives", "agreeing", "disagreeing", "curated"):
        assert summary[key] == from_float32[key], key
    assert summary["disagreeing"] == 0 and summary["agreeing"] > 0
    for table in ("mechanisms", "negatives", "paths", "curated"):
        assert read_table(root, table) == read_table(imported[0], table), table


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (
            lambda x: np.full(x.shape, 2**62, dtype=np.int64),
            r"x_sol must be \(\d+, 200, 2\) float16, float32 or float64, got \(\d+, 200, 2\) int64",
        ),
        (
            lambda x: np.where(np.arange(200)[None, :, None] == 7, np.nan, x),
            r"x_sol must be finite, and holds NaN or infinity",
        ),
        (lambda x: x[:, :199], r"x_sol must be \(\d+, 200, 2\) .*, got \(\d+, 199, 2\) float32"),
        (lambda x: x.astype(np.complex64), r"at byte \d+ is not a readable pickle: dtype"),
    ],
)
def test_a_trajectory_that_is_no_real_float_is_one_line(
    tmp_path: Path, make: Any, message: str
) -> None:
    """An int (whatever its values), a NaN, a wrong shape or a complex trajectory: one line
    naming the simulation file and the batch (and the index, or the offset where the pickle
    itself is refused)."""
    write_release(tmp_path, BATCHES[:2])
    store = Store.open(str(tmp_path), writable=False)
    batches = [batch for _, _, batch in read_batches(store, "simulation_dataset")]
    batches[1][2][0] = make(batches[1][2][0])
    with open(tmp_path / "simulation_dataset", "wb") as out:
        for batch in batches:
            pickle.dump(batch, out)
    with pytest.raises(ReleaseFileError) as raised:
        import_release(str(tmp_path), str(tmp_path / "root"))
    said = str(raised.value)
    assert "\n" not in said
    assert said.startswith(f"{tmp_path}/simulation_dataset batch 1 ")
    assert re.search(message, said), said
    if "index" in said:
        assert said.startswith(f"{tmp_path}/simulation_dataset batch 1 index 2: ")


def test_a_mechanism_links_ray_refuses_names_the_batch_and_index(tmp_path: Path) -> None:
    bad = [list(BATCHES[0])]
    a, x0, fixed = bad[0][4]
    a = a.copy()
    a[0, 2] = True  # no longer symmetric
    bad[0][4] = (a, x0, fixed)
    with open(tmp_path / "dataset", "wb") as out:
        pickle.dump([list(e) for e in bad[0]], out)
    with pytest.raises(ReleaseFileError, match="batch 0 index 4: adjacency is not symmetric"):
        import_release(str(tmp_path), str(tmp_path / "root"))


# -- the import ---------------------------------------------------------------------------------


def test_mechanisms_keep_their_release_positions_and_map_their_joints(
    imported: tuple[str, dict],
) -> None:
    root, summary = imported
    rows = read_table(root, "mechanisms")
    negatives = read_table(root, "negatives")
    total = sum(map(len, BATCHES))
    assert len(rows) + len(negatives) == total == summary["imported"]
    for mechanism_id, row in rows.items():
        b, j = place(mechanism_id)
        a, x0, fixed = BATCHES[b][j]
        n = len(fixed)
        positions = np.array(row["positions"]).reshape(n, 2)
        assert positions.tobytes() == x0.astype(np.float64).tobytes()
        np.testing.assert_array_equal(np.array(row["adjacency"]).reshape(n, n), a)
        types = np.array(row["node_types"])
        assert types[0] == 0 and types[1] == 2
        np.testing.assert_array_equal(types == 0, fixed)
        assert set(types[2:].tolist()) <= {0, 1}
        assert row["topology_id"] == mechanism_id // 5 and row["variant"] == mechanism_id % 5
    # The four-bars that lock in links-ray's turn are negatives, with their places; the first
    # only between the sampled steps 1 and 2, as generation's check finds.
    assert sorted(negatives) == [
        NEGATIVE_ID_BASE + BATCH_STRIDE * 2 + len(BATCHES[2]) - k for k in (2, 1)
    ]
    between, locked = (negatives[i] for i in sorted(negatives))
    assert list(place(between["mechanism_id"])) == [2, len(BATCHES[2]) - 2]
    assert between["locked_step"] == 2
    assert locked["locked_step"] >= 0


def test_summary_counts_the_check_against_the_release(imported: tuple[str, dict]) -> None:
    _, summary = imported
    released = sum(release_simulation(*entry) is not None for batch in BATCHES for entry in batch)
    assert summary["agreeing"] == released == sum(map(len, BATCHES)) - 1
    assert summary["disagreeing"] == 0 and summary["unchecked"] == 0
    assert summary["locking_at_release_angles"] == 1
    assert summary["negatives"] == 2
    assert summary["topologies"] == sum(-(-len(batch) // 5) for batch in BATCHES)
    assert 0 < summary["worst_error"] < 1e-5
    assert summary["curated_from"] == "release"


def test_a_release_trajectory_that_disagrees_is_kept_and_flagged(tmp_path: Path) -> None:
    write_release(tmp_path, BATCHES[:1])
    store = Store.open(str(tmp_path), writable=False)
    (solutions,) = [value for _, _, value in read_batches(store, "simulation_dataset")]
    solutions[6][0][3, 40:, :] += 0.05  # joint 3 of mechanism j strays from step 40
    j = solutions[6][1]
    with open(tmp_path / "simulation_dataset", "wb") as out:
        pickle.dump(solutions, out)
    summary = import_release(str(tmp_path), str(tmp_path / "root"))
    assert summary["disagreeing"] == 1 and summary["disagreeing_ids"] == [j]
    size = np.ptp(BATCHES[0][j][1].astype(np.float64), axis=0).max()
    assert summary["worst_error"] == pytest.approx(0.05 / size, rel=1e-3)
    assert j in read_table(str(tmp_path / "root"), "mechanisms")


def test_paths_are_curations_and_curated_are_the_releases_pairs(
    imported: tuple[str, dict],
) -> None:
    root, summary = imported
    store = Store.open(root, writable=False)
    paths = read_table(root, "paths")
    expected = {}
    for relative in committed_files(store, "mechanisms"):
        table = store.read_parquet(relative)
        n = len(table.column("node_types")[0].as_py())
        for row in path_table(table, None, n).to_pylist():
            expected[row["path_id"]] = row
    assert paths == expected
    curated = read_table(root, "curated")
    named = {(b, j, node) for b, batch in enumerate(CURATED) for j, node in batch}
    # A pair naming a fixed joint has no path: counted, not curated.
    pairs = {(b, j, node) for b, j, node in named if not BATCHES[b][j][2][node]}
    assert 0 < len(pairs) < len(named)
    got = set()
    for row in curated.values():
        b, j = place(row["mechanism_id"])
        got.add((b, j, row["joint"]))
        assert row == paths[row["path_id"]]
    assert got == pairs
    assert summary["curated"] == len(pairs)
    assert summary["release_curated_unmatched"] == len(named) - len(pairs)


def test_without_curated_dataset_the_seeded_choice_curates(tmp_path: Path) -> None:
    write_release(tmp_path, BATCHES[:1])
    summary = import_release(str(tmp_path), str(tmp_path / "root"), seed=3)
    assert summary["curated_from"] == "seed"
    paths = read_table(str(tmp_path / "root"), "paths")
    curated = read_table(str(tmp_path / "root"), "curated")
    plain = {i for i, row in paths.items() if not (row["is_arc"] or row["is_circle"])}
    assert plain and plain <= set(curated) < set(paths)


def test_resume_after_a_failure_between_batches_gives_the_same_rows(
    release: Path, imported: tuple[str, dict], tmp_path: Path
) -> None:
    root = str(tmp_path / "root")

    def stop(step: str) -> None:
        if step == "batch 1 committed":
            raise RuntimeError("stopped")

    with pytest.raises(RuntimeError, match="stopped"):
        import_release(str(release), root, failpoint=stop)
    partial = read_table(root, "mechanisms")
    assert 0 < len(partial) < len(read_table(imported[0], "mechanisms"))
    summary = import_release(str(release), root)
    for table in ("mechanisms", "negatives", "paths", "curated"):
        assert read_table(root, table) == read_table(imported[0], table), table
    keys = ("mechanisms", "negatives", "agreeing", "paths", "curated", "worst_error")
    assert {k: summary[k] for k in keys} == {k: imported[1][k] for k in keys}
    # Once finished, the same command commits nothing more: every shard exactly once.
    files = sorted(str(path) for path in Path(root).rglob("*.parquet"))
    again = import_release(str(release), root)
    assert sorted(str(path) for path in Path(root).rglob("*.parquet")) == files
    assert {k: again[k] for k in keys} == {k: summary[k] for k in keys}


def test_resume_after_a_failure_inside_a_shard_gives_the_same_rows(
    release: Path,
    imported: tuple[str, dict],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Batch 1's first shard fails after its rows are written, before its paths commit: its
    generation shard is committed, its curation shard not."""
    root = str(tmp_path / "root")

    class FailingWriter(ShardWriter):
        def commit(self, stats: dict) -> dict:
            if self.stage == "curation" and self.shard_id // SHARDS_PER_BATCH == 1:
                raise OSError("the store went away")
            return super().commit(stats)

    monkeypatch.setattr(import_shards, "ShardWriter", FailingWriter)
    with pytest.raises(OSError, match="the store went away"):
        import_release(str(release), root)
    monkeypatch.undo()
    store = Store.open(root, writable=False)
    generated, curated = committed_shards(store, "shards"), committed_shards(store, "curation")
    assert set(curated) < set(generated)
    assert not list(Path(root).rglob("_shard-*"))  # the failed attempt left nothing
    import_release(str(release), root)
    for table in ("mechanisms", "negatives", "paths", "curated"):
        assert read_table(root, table) == read_table(imported[0], table), table


def test_an_import_beside_a_running_writer_is_refused(release: Path, tmp_path: Path) -> None:
    store = Store.open(str(tmp_path / "root"))
    with Lease.acquire(store, "writer", "links generate"):
        with pytest.raises(LeaseHeld, match="is in use by links generate"):
            import_release(str(release), str(tmp_path / "root"))
    assert not read_table(str(tmp_path / "root"), "mechanisms")


def test_import_from_s3_equals_the_folders(
    s3_env: str, release: Path, imported: tuple[str, dict], tmp_path: Path
) -> None:
    import boto3

    bucket = s3_env.removeprefix("s3://")
    client = boto3.client("s3")
    for path in release.iterdir():
        client.upload_file(str(path), bucket, f"release/{path.name}")
    root = str(tmp_path / "root")
    summary = import_release(f"{s3_env}/release", root)
    assert summary["mechanisms"] == imported[1]["mechanisms"]
    for table in ("mechanisms", "negatives", "curated"):
        assert read_table(root, table) == read_table(imported[0], table), table


def test_ids_stay_within_a_batch() -> None:
    ids = BATCH_STRIDE * np.array([0, 3, 7]) + np.array([4, 99_999, 0])
    batches, indices = release_location(ids)
    assert batches.tolist() == [0, 3, 7] and indices.tolist() == [4, 99_999, 0]
    assert (BATCH_STRIDE % 5) == 0


# -- the root in use --------------------------------------------------------------------------


def test_stats_retrieval_and_synthesis_work_on_the_imported_root(
    imported: tuple[str, dict],
) -> None:
    from links_ray.data.stats import dataset_stats
    from links_ray.engine.synthesis.pipeline import synthesize
    from links_ray.search.index import RetrievalIndex

    root, summary = imported
    stats = dataset_stats(root)
    assert stats["counts"]["mechanisms"]["rows"] == summary["mechanisms"]
    assert stats["counts"]["curated"]["rows"] == summary["curated"]
    index = RetrievalIndex.open(root)
    curated = read_table(root, "curated")
    target = next(iter(curated.values()))
    query = np.array(target["points"]).reshape(-1, 2) * 3 + 1
    results = index.retrieve(query, k=3)
    assert results[0]["path_id"] == target["path_id"]
    assert results[0]["chamfer"] < 1e-3
    exact = index.brute_force(query, k=3)
    assert [r["path_id"] for r in results] == [int(index.path_id[row]) for row, _, _ in exact]
    found = synthesize(index, query, k=2, seed=0, iterations=20)
    assert len(found) == 2
    # The curve is an imported mechanism's own: synthesis finds it again.
    assert found[0]["chamfer"] < 1e-4
    assert {r["path_id"] for r in found} <= {r["path_id"] for r in index.retrieve(query, k=50)}


def test_stats_retrieve_and_synthesize_commands_on_the_imported_root(
    imported: tuple[str, dict], tmp_path: Path
) -> None:
    """The commands as a user types them: stats counts the imported rows; retrieve and
    synthesize find an imported mechanism of the second release batch by its own curve."""
    root, summary = imported

    def answer(*args: str) -> dict:
        done = links(*args, "--json")
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout)

    stats = answer("stats", root)
    assert stats["counts"]["curated"]["rows"] == summary["curated"]
    assert stats["counts"]["mechanisms"]["rows"] == summary["mechanisms"]
    (target,) = [
        row for row in read_table(root, "curated").values() if place(row["mechanism_id"]) == (1, 12)
    ]
    points = tmp_path / "curve.json"
    points.write_text(json.dumps((np.array(target["points"]).reshape(-1, 2) * 2 - 1).tolist()))
    found = answer("retrieve", root, "--points", str(points))["results"]
    assert found[0]["mechanism_id"] == target["mechanism_id"] and found[0]["chamfer"] < 1e-3
    work = ("--iterations", "20", "--seed", "0")
    made = answer("synthesize", root, "--points", str(points), "-k", "2", *work)["results"]
    assert made[0]["chamfer"] < 1e-4


def test_generating_or_curating_into_an_imported_root_is_refused(
    imported: tuple[str, dict],
) -> None:
    """Its curated set is the release's: a seeded pass would mix another into it."""
    from links_ray.cluster.curation import curate
    from links_ray.cluster.generation import generate

    root, summary = imported
    said = "is an import of the LINKS release: only links import-release writes to it"
    with pytest.raises(StoreError, match=said):
        curate(root, progress=False)
    with pytest.raises(StoreError, match=said):
        generate(root, 10, progress=False)
    assert len(read_table(root, "curated")) == summary["curated"]


def test_ray_dataset_streams_the_imported_root(
    imported: tuple[str, dict], ray_cluster: str
) -> None:
    from links_ray.cluster.datasets import ray_dataset

    root, summary = imported
    curated = read_table(root, "curated")
    rows = ray_dataset(root, "curated", columns=["path_id", "mechanism_id", "joint"])
    got = rows.take_all()
    assert len(got) == summary["curated"] and sorted(r["path_id"] for r in got) == sorted(curated)
    assert {(r["path_id"], r["mechanism_id"], r["joint"]) for r in got} == {
        (i, row["mechanism_id"], row["joint"]) for i, row in curated.items()
    }
    mechanisms = ray_dataset(root, "mechanisms", n_joints=6, columns=["mechanism_id"])
    six = [i for i, row in read_table(root, "mechanisms").items() if len(row["node_types"]) == 6]
    assert sorted(r["mechanism_id"] for r in mechanisms.take_all()) == sorted(six) != []


# `links serve` starts a Ray of its own: with the tests that need Ray, one at a time. Beside
# another test's work (tests/run's second step runs two at once) its shutdown outlasted 120 s.
@pytest.mark.ray
def test_links_serve_and_the_studio_work_on_the_imported_root(
    imported: tuple[str, dict], browser: Any, tmp_path: Path
) -> None:
    """`links serve` on the imported root: retrieval finds an imported mechanism of the last
    release batch by its own curve, synthesis refines to it, and the studio draws, retrieves
    and opens it as the API answers."""
    root, summary = imported
    curated = read_table(root, "curated")
    # Of the last batch, and no crank's circle (which every mechanism's joint 1 traces).
    (target,) = [row for row in curated.values() if place(row["mechanism_id"]) == (2, 9)]
    assert not target["is_circle"]
    points = np.array(target["points"]).reshape(-1, 2)
    # In the drawing area's middle (retrieval does not see where, or how large).
    curve = 0.25 + 0.5 * (points - points.min(0)) / np.ptp(points, axis=0).max()
    port = bindable_port("127.0.0.1", 0)
    with links_serve(root, port, tmp_path / "stderr.txt") as client:
        status, health = client.get("/api/health")
        assert status == 200 and health["paths"] == summary["curated"]
        status, found = client.post("/api/retrieve", {"points": curve.tolist(), "k": 3})
        assert status == 200, found
        best = found["results"][0]
        assert best["mechanism_id"] == target["mechanism_id"] and best["chamfer"] < 1e-3
        # Whatever its transmission angle: no floor, so the imported mechanism is a candidate.
        request = {
            "points": curve.tolist(),
            "k": 2,
            "seed": 0,
            "iterations": 20,
            "min_transmission": 0,
        }
        status, made = client.post("/api/synthesize", request)
        assert status == 200, made
        assert made["results"][0]["chamfer"] < 1e-4

        with open_studio(browser, port) as studio:
            draw(studio, curve.tolist())
            drawn = studio.js("() => window.studio.retriever.points")
            studio.page.get_by_test_id("k").fill("3")
            studio.page.get_by_test_id("min-transmission").fill("0")
            studio.click("retrieve-button")
            results = studio.page.get_by_test_id("result")
            results.nth(2).wait_for()
            _, expected = client.post("/api/retrieve", {"points": drawn, "k": 3})
            chamfers = [float(results.nth(i).get_attribute("data-chamfer")) for i in range(3)]
            assert chamfers == [r["chamfer"] for r in expected["results"]]
            # Drawn by hand (a mouse), the curve still finds its mechanism first.
            assert expected["results"][0]["mechanism_id"] == target["mechanism_id"]
            results.nth(0).click()
            studio.wait(
                "() => document.querySelector('[data-testid=draw-canvas]')"
                ".dataset.animating === 'true'"
            )
            chosen = studio.js("() => window.studio.retriever.chosen")
            assert chosen["result"]["mechanism"] == expected["results"][0]["mechanism"]
            studio.click("open-in-editor")
            studio.wait_idle()
            assert studio.mechanism() == expected["results"][0]["mechanism"]


def test_the_command_prints_its_summary(ray_cluster: str, tmp_path: Path) -> None:
    write_release(tmp_path / "release", BATCHES[:1])
    command = [
        *(sys.executable, "-m", "links_ray.cli", "import-release", str(tmp_path / "release")),
        *("--address", ray_cluster),
    ]
    line = subprocess.run(
        [*command, "--out", str(tmp_path / "a")], capture_output=True, text=True, check=True
    ).stdout
    count = len(BATCHES[0])
    assert line.startswith(f"{count} mechanisms and 0 negatives from 1 release batches; ")
    assert f"{count} agree, 0 disagree, 0 lock, 0 unchecked; " in line
    assert "(the seeded choice)" in line and line.count("\n") == 1
    summary = json.loads(
        subprocess.run(
            [*command, "--out", str(tmp_path / "b"), "--json"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    )
    assert summary["mechanisms"] == count and summary["curated_from"] == "seed"


# -- round trip ---------------------------------------------------------------------------------


def committed_table(root: str, name: str) -> pa.Table:
    """A root's committed `name` table, by mechanism_id."""
    store = Store.open(root, writable=False)
    tables = [store.read_parquet(f) for f in committed_files(store, name)]
    return pa.concat_tables(tables).sort_by("mechanism_id")


def test_export_then_import_keeps_the_mechanisms_and_the_curated_set(
    dataset: str, tmp_path: Path
) -> None:
    """A generated and curated root exported in the release's layout and imported again: every
    mechanism comes back, in mechanism_id order batch by batch, with its adjacency, node types
    and positions as the release holds them (float32), and the curated set is the source's."""
    from links_ray.release.exporter import export_release

    out = tmp_path / "release"
    export_release(dataset, str(out), chunk_size=128, format="release")
    root = tmp_path / "root"
    summary = import_release(str(out), str(root))
    assert summary["curated_from"] == "release"
    source = committed_table(dataset, "mechanisms")
    back = committed_table(str(root), "mechanisms")
    assert len(back) == len(source) > 128  # more than one batch
    batch, index = release_location(back.column("mechanism_id").to_numpy())
    order = batch * 128 + index  # each one's place in the source's mechanism_id order
    for column in ("adjacency", "node_types"):
        expected = [source.column(column)[int(i)].as_py() for i in order]
        assert back.column(column).to_pylist() == expected
    for i, positions in zip(order, back.column("positions").to_pylist(), strict=True):
        held = np.float32(source.column("positions")[int(i)].as_py()).astype(np.float64)
        np.testing.assert_array_equal(positions, held)
    source_id = dict(
        zip(
            back.column("mechanism_id").to_pylist(),
            source.column("mechanism_id").to_numpy()[order].tolist(),
            strict=True,
        )
    )
    curated = committed_table(dataset, "curated")
    imported = committed_table(str(root), "curated")
    wanted = set(
        zip(curated["mechanism_id"].to_pylist(), curated["joint"].to_pylist(), strict=True)
    )
    got = {
        (source_id[m], j)
        for m, j in zip(
            imported["mechanism_id"].to_pylist(), imported["joint"].to_pylist(), strict=True
        )
    }
    assert got == wanted and len(wanted) > 0
