"""`links_ray.ray_dataset`: a table's committed rows as a Ray Dataset, the same rows `load`
reads, filtered by joint count and by any column, streamed in batches."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pyarrow.dataset as pads
import pytest

import links_ray


def _ids(table: object, column: str) -> list[int]:
    return sorted(int(i) for i in table[column])


def test_the_rows_are_loads_rows(dataset: str) -> None:
    rows = links_ray.ray_dataset(dataset, "mechanisms").to_pandas()
    expected = links_ray.load(dataset, "mechanisms")
    assert len(rows) == len(expected) == 300
    assert _ids(rows, "mechanism_id") == _ids(expected, "mechanism_id")
    assert set(rows["n_joints"]) == set(expected["n_joints"])
    first = rows.sort_values("mechanism_id").iloc[0]
    truth = expected.sort_values("mechanism_id").iloc[0]
    np.testing.assert_array_equal(first["positions"], truth["positions"])


def test_filters_on_joint_count_and_any_column(dataset: str) -> None:
    counts = sorted(set(links_ray.load(dataset, "curated", columns=["n_joints"])["n_joints"]))
    wanted = counts[:2]
    floor = 5.0
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        rows = links_ray.ray_dataset(
            dataset,
            "curated",
            n_joints=wanted,
            columns=["path_id", "min_transmission_deg", "n_joints"],
            filter=pads.field("min_transmission_deg") >= floor,
        ).to_pandas()
    # Ray names the caller of what it deprecates: none of it is ours.
    assert [str(w.message) for w in seen if "links_ray" in w.filename] == []
    expected = links_ray.load(dataset, "curated", n_joints=wanted)
    expected = expected[expected["min_transmission_deg"] >= floor]
    assert 0 < len(rows) == len(expected)
    assert _ids(rows, "path_id") == _ids(expected, "path_id")
    assert set(rows["n_joints"]) <= set(wanted)
    assert list(rows.columns) == ["path_id", "min_transmission_deg", "n_joints"]


def test_batches_stream_as_numpy(dataset: str) -> None:
    """`iter_batches` hands a training loop numpy arrays, a fixed number of paths a batch."""
    data = links_ray.ray_dataset(dataset, "curated", columns=["path_id", "points"])
    seen = 0
    for batch in data.iter_batches(batch_size=64, batch_format="numpy"):
        points = np.stack(batch["points"]).reshape(len(batch["path_id"]), -1, 2)
        assert points.shape[1:] == (200, 2) and len(points) <= 64
        seen += len(points)
    assert seen == len(links_ray.load(dataset, "curated", columns=["path_id"]))


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"table": "nope"}, "table must be one of"),
        ({"table": "mechanisms", "columns": ["nope"]}, "has no column nope"),
        ({"table": "mechanisms", "n_joints": 3}, "no mechanisms rows of [3] joints"),
        ({"table": "mechanisms", "n_joints": "8"}, "n_joints must be an integer"),
        ({"table": "mechanisms", "filter": "n_joints > 8"}, "filter must be a pyarrow"),
    ],
)
def test_bad_arguments_are_value_errors(dataset: str, arguments: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        links_ray.ray_dataset(dataset, **arguments)


def test_a_root_without_the_table_is_a_value_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="has no mechanisms table"):
        links_ray.ray_dataset(str(tmp_path), "mechanisms")


def test_the_read_starts_no_listing_threads(dataset: str, capsys: pytest.CaptureFixture) -> None:
    """The files are read as the commit markers list them, with no second listing by Ray Data:
    its listing task runs threads whose signaller can die at the task's end (the race below),
    and their traceback then lands in the caller's output (notebook 04 once failed on it)."""
    data = links_ray.ray_dataset(dataset, "curated", n_joints=[8, 9], split="train")
    capsys.readouterr()
    data.explain()
    plan = capsys.readouterr().out
    assert "ReadParquet" in plan and "ListFiles" not in plan, plan
    # The read itself leaves the caller's choice of reader as it was.
    import ray

    assert ray.data.DataContext.get_current().use_datasource_v2


def test_ray_datas_threaded_listing_still_races() -> None:
    """The cause the read above steps around, with no Ray running: Ray Data's work-stealing
    pool (the threaded file listing) lets its completion signaller put its sentinels after
    the consumer, done, has set the pool's interrupt; the signaller's thread then dies of an
    InterruptedError that threading prints as a traceback. Frequent thread switches make the
    race show within a few runs. When this test fails, a Ray upgrade has mended the race."""
    import sys
    import threading

    from ray.data._internal.dynamic_work_queue import parallel_process_work_stealing

    died: list[str] = []
    hook, interval = threading.excepthook, sys.getswitchinterval()
    threading.excepthook = lambda args: died.append(f"{args.thread.name}: {args.exc_type}")
    sys.setswitchinterval(1e-6)
    try:
        for run in range(100):
            found = parallel_process_work_stealing(
                [run], lambda item, add_work, add_result: add_result(item), num_workers=8
            )
            assert list(found) == [run]
            if died:
                break
    finally:
        sys.setswitchinterval(interval)
        threading.excepthook = hook
    assert died and "completion-signaler" in died[0] and "InterruptedError" in died[0], died


@pytest.fixture(scope="module")
def lean_and_stored(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, str]:
    """One plan written with every table, and as mechanisms and curated ids (a lean root)."""
    from tests.support.local_dataset import stored_and_lean

    folder = str(tmp_path_factory.mktemp("lean-ray"))
    stored, lean = stored_and_lean(folder, seed=13, mechanisms=40, topologies_per_shard=2)
    return lean, stored


def _all_rows(data: object, key: str) -> object:
    import pyarrow as pa
    import ray

    return pa.concat_tables(ray.get(data.to_arrow_refs())).sort_by(key)


@pytest.mark.parametrize(
    ("table", "key"),
    [("curated", "path_id"), ("paths", "path_id"), ("simulations", "mechanism_id")],
)
def test_a_lean_roots_rows_are_derived_as_stored(
    ray_cluster: str, lean_and_stored: tuple[str, str], table: str, key: str
) -> None:
    """Rows a lean root does not store stream from tasks that derive them, equal bit for bit
    to the stored rows of the same run; by joint count and split too."""
    lean, stored = lean_and_stored
    derived = _all_rows(links_ray.ray_dataset(lean, table), key)
    expected = _all_rows(links_ray.ray_dataset(stored, table), key)
    assert len(expected) > 0 and derived.schema == expected.schema
    assert derived.equals(expected)
    counts = links_ray.load(stored, "mechanisms", columns=["n_joints"])["n_joints"]
    for some in ({"n_joints": int(counts.mode()[0])}, {"split": "train"}):
        some = {**some, "columns": [key, "n_joints"]}
        derived = _all_rows(links_ray.ray_dataset(lean, table, **some), key).to_pydict()
        expected = _all_rows(links_ray.ray_dataset(stored, table, **some), key).to_pydict()
        assert len(expected[key]) > 0 and derived == expected, some
