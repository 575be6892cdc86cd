"""The commit protocol under faults, on real files: a local folder and the SeaweedFS S3 server.

A shard's commit is a sequence of steps (close the files, move each table's file, write the
marker). A failure is injected after each step, both as an exception (the writer aborts) and as
a killed process (nothing runs after the step). Readers must see only committed rows throughout,
and finishing the work must give exactly the rows of an undisturbed run.
"""

from __future__ import annotations

import dataclasses
import http.server
import json
import os
import queue
import shutil
import subprocess
import sys
import textwrap
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as pads
import pytest

import links_ray
from links_ray.data.commit import (
    Failpoint,
    ShardWriter,
    committed_files,
    committed_shards,
    marker_file,
    remove_uncommitted,
)
from links_ray.data.dataset import PARTITIONING, open_table
from links_ray.data.generation import GenerationPlan, Shard, generate_shard, write_shard
from links_ray.data.schemas import GENERATION_TABLES
from links_ray.data.store import Store, StoreError
from tests.support.cli import links

#: Four topologies of four joint counts: four shards of one topology each.
PLAN = GenerationPlan(seed=3, mechanisms=20, topologies_per_shard=1)
#: The steps of a generation shard's commit, in order.
STEPS = ["closed", "moved mechanisms", "moved simulations", "moved negatives", "marked"]


class InjectedFault(OSError):
    """The failure a test injects into a commit."""


def fail_at(step: str) -> Failpoint:
    def failpoint(reached: str) -> None:
        if reached == step:
            raise InjectedFault(f"injected after {step!r}")

    return failpoint


def rows(root: str | Store) -> dict[str, pa.Table]:
    """Every generation table's committed rows, through `load`, sorted by id."""
    return {
        table: links_ray.load(root, table, format="arrow").sort_by("mechanism_id")
        for table in GENERATION_TABLES
    }


def plain_rows(store: Store, table: str) -> pa.Table:
    """What a plain pyarrow directory read of `table` shows."""
    return pads.dataset(
        store.path(table), filesystem=store.fs, partitioning=PARTITIONING
    ).to_table()


def hidden_files(store: Store) -> list[str]:
    return [f for t in GENERATION_TABLES for f in store.list_files(t) if "/_" in f]


def table_files(store: Store) -> list[str]:
    """Every file below the generation tables' folders, sorted."""
    return sorted(f for t in GENERATION_TABLES for f in store.list_files(t))


def committed_names(store: Store) -> list[str]:
    """The files the generation markers name, sorted."""
    return sorted(f for t in GENERATION_TABLES for f in committed_files(store, t))


def assert_same(a: dict[str, pa.Table], b: dict[str, pa.Table]) -> None:
    for table in GENERATION_TABLES:
        assert a[table].equals(b[table]), f"{table} differs"


@pytest.fixture(scope="module")
def undisturbed(tmp_path_factory: pytest.TempPathFactory) -> dict[str, pa.Table]:
    """The rows of every shard of PLAN, committed without a fault."""
    store = Store.open(str(tmp_path_factory.mktemp("undisturbed") / "data"))
    for shard in PLAN.shards():
        write_shard(store, PLAN, shard)
    return rows(store)


def first_shard_only(tables: dict[str, pa.Table]) -> dict[str, pa.Table]:
    shard = PLAN.shards()[0]
    ids = pa.array([5 * t + v for t in shard.topology_ids() for v in range(5)])
    out = {}
    for table, rows_ in tables.items():
        topology = rows_.column("topology_id") if "topology_id" in rows_.column_names else None
        if topology is None:
            out[table] = rows_.filter(pc.is_in(rows_.column("mechanism_id"), ids))
        else:
            out[table] = rows_.filter(pc.is_in(topology, pa.array(list(shard.topology_ids()))))
    return out


@pytest.fixture(params=["local", "s3"])
def root(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    if request.param == "local":
        return str(tmp_path / "data")
    return f"{request.getfixturevalue('s3_env')}/data"


@pytest.mark.parametrize("step", STEPS[:-1])
def test_a_failed_commit_shows_nothing_and_is_redone(
    root: str, step: str, undisturbed: dict[str, pa.Table]
) -> None:
    store = Store.open(root)
    first, second, *rest = PLAN.shards()
    write_shard(store, PLAN, first)
    with pytest.raises(InjectedFault, match=f"injected after '{step}'"):
        write_shard(store, PLAN, second, failpoint=fail_at(step))
    # The original error came through the abort, which left nothing behind, visible or hidden.
    assert_same(rows(store), first_shard_only(undisturbed))
    assert len(plain_rows(store, "mechanisms")) == len(first_shard_only(undisturbed)["mechanisms"])
    assert hidden_files(store) == []
    for shard in (second, *rest):
        write_shard(store, PLAN, shard)
    assert_same(rows(store), undisturbed)


KILLED_WRITER = textwrap.dedent(
    """
    import os, sys
    from links_ray.data.generation import GenerationPlan, Shard, generate_shard, write_shard
    from links_ray.data.store import Store

    root, step = sys.argv[1], sys.argv[2]
    plan = GenerationPlan(seed=3, mechanisms=20, topologies_per_shard=1)

    def die(reached):
        if reached == step:
            os._exit(17)  # the process ends here: no abort, no cleanup

    write_shard(Store.open(root), plan, plan.shards()[1], failpoint=die)
    """
)


@pytest.mark.parametrize("step", STEPS)
def test_a_writer_killed_mid_commit_shows_nothing_until_redone(
    root: str, step: str, undisturbed: dict[str, pa.Table]
) -> None:
    store = Store.open(root)
    first, second, *rest = PLAN.shards()
    write_shard(store, PLAN, first)
    killed = subprocess.run(
        [sys.executable, "-c", KILLED_WRITER, root, step],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(Path(links_ray.__file__).parents[1])},
    )
    assert killed.returncode == 17, killed.stderr
    if step == "marked":  # the marker was written: the shard is committed
        assert set(committed_shards(store)) == {first.shard_id, second.shard_id}
    else:
        assert_same(rows(store), first_shard_only(undisturbed))
        assert set(committed_shards(store)) == {first.shard_id}
    # The next run: its cleanup at the start removes the killed attempt's hidden files. Files
    # it moved stay while their shard has no marker (a live attempt's would be about to commit).
    done = committed_shards(store)
    remove_uncommitted(store, "shards", done)
    assert hidden_files(store) == []
    assert set(committed_names(store)) <= set(table_files(store))
    moved = [f for f in table_files(store) if f not in committed_names(store)]
    assert len(moved) == (STEPS.index(step) if step != "marked" else 0)
    for shard in (second, *rest):
        if shard.shard_id not in done:
            write_shard(store, PLAN, shard)
    # ... and its cleanup at the end, the shard committed again, the killed attempt's rest.
    remove_uncommitted(store, "shards", committed_shards(store))
    assert table_files(store) == committed_names(store)
    assert_same(rows(store), undisturbed)
    assert_same(
        {t: plain_rows(store, t).sort_by("mechanism_id") for t in GENERATION_TABLES},
        undisturbed,
    )


def test_abort_does_not_mask_the_error_when_the_store_is_gone(tmp_path: Path) -> None:
    store = Store.open(str(tmp_path / "data"))
    shard = PLAN.shards()[0]

    def vanish(step: str) -> None:
        if step == "moved simulations":
            shutil.rmtree(tmp_path / "data")  # what abort would delete is gone already
            raise InjectedFault("the disk went away")

    writer = ShardWriter(store, shard.shard_id, shard.n_joints, failpoint=vanish)
    stats = generate_shard(PLAN, shard, writer.write)
    with pytest.raises(InjectedFault, match="the disk went away"):
        try:
            writer.commit(stats)
        except BaseException:
            writer.abort()
            raise


def test_an_unreadable_marker_counts_as_absent(tmp_path: Path) -> None:
    store = Store.open(str(tmp_path / "data"))
    for shard in PLAN.shards()[:2]:
        write_shard(store, PLAN, shard)
    damaged = store.path(marker_file(1))
    Path(damaged).write_text('{"shard": 1, "files": {"mechanisms": "mechan')
    assert set(committed_shards(store)) == {0}
    assert committed_files(store, "mechanisms") == [
        committed_shards(store)[0]["files"]["mechanisms"]
    ]
    Path(damaged).write_text(json.dumps({"shard": 1, "files": "not a mapping"}))
    assert set(committed_shards(store)) == {0}
    assert len(links_ray.load(store, "mechanisms")) == 5


def test_readers_refuse_a_root_with_no_committed_rows(tmp_path: Path) -> None:
    store = Store.open(str(tmp_path / "data"))
    shard = PLAN.shards()[0]
    with pytest.raises(InjectedFault):
        write_shard(store, PLAN, shard, failpoint=fail_at("moved negatives"))
    with pytest.raises(ValueError, match="has no mechanisms table yet"):
        open_table(store, "mechanisms")


SMALL_FILE_WRITER = textwrap.dedent(
    """
    import sys
    from links_ray.data.store import Store

    store = Store.open(sys.argv[1])
    block = bytes(range(256)) * (1 << 16)  # 16 MiB
    version = 0
    while True:
        version = (version + 1) % 256
        store.write_bytes("_links/index.npz", bytes([version]) * 64 + block)
        print(version, flush=True)
    """
)


def test_a_small_file_is_whole_after_its_writer_is_killed(tmp_path: Path) -> None:
    root = str(tmp_path / "data")
    Store.open(root)
    block = bytes(range(256)) * (1 << 16)
    writer = subprocess.Popen(
        [sys.executable, "-c", SMALL_FILE_WRITER, root],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(Path(links_ray.__file__).parents[1])},
    )
    for _ in range(3):  # a few whole writes, then a kill at an arbitrary moment of the next
        writer.stdout.readline()
    writer.kill()
    writer.wait()
    data = (tmp_path / "data" / "_links" / "index.npz").read_bytes()
    assert len(data) == 64 + len(block) and data[64:] == block
    assert len(set(data[:64])) == 1


def named_files_exist(store: Store, marker: dict) -> bool:
    return all(store.read_bytes(relative) is not None for relative in marker["files"].values())


def test_an_attempt_failing_beside_a_committing_one_leaves_its_commit_whole(
    root: str, undisturbed: dict[str, pa.Table]
) -> None:
    """Attempt A fails after moving its first file; attempt B of the same shard commits between
    A's look for a marker and A's cleanup. B's commit must stay whole."""
    first = PLAN.shards()[0]
    store_a, store_b = Store.open(root), Store.open(root)
    committed_during_abort = []
    read_json = store_a.read_json

    def read_then_let_b_commit(relative: str) -> dict | None:
        value = read_json(relative)
        if relative == marker_file(first.shard_id) and not committed_during_abort:
            committed_during_abort.append(write_shard(store_b, PLAN, first))
        return value

    store_a.read_json = read_then_let_b_commit  # type: ignore[method-assign]
    with pytest.raises(InjectedFault):
        write_shard(store_a, PLAN, first, failpoint=fail_at("moved mechanisms"))
    assert committed_during_abort, "B never ran inside A's abort"
    marker = committed_shards(store_b)[first.shard_id]
    assert named_files_exist(store_b, marker), marker["files"]
    assert_same(rows(store_b), first_shard_only(undisturbed))


class Attempt:
    """One attempt at a shard, on a thread of its own, stopping after each of its steps until
    told to go on (or to fail there)."""

    def __init__(self, store: Store, shard: Shard, batches: list, stats: dict) -> None:
        self.writer = ShardWriter(store, shard.shard_id, shard.n_joints, failpoint=self._stop)
        self.steps: list[str] = []
        self.result: dict | None = None
        self.error: BaseException | None = None
        self._stopped: queue.Queue[str | None] = queue.Queue()
        self._orders: queue.Queue[str] = queue.Queue()
        self._thread = threading.Thread(target=self._run, args=(batches, stats), daemon=True)
        self.done = False

    def _stop(self, step: str) -> None:
        self.steps.append(step)
        self._stopped.put(step)
        if self._orders.get() == "fail":
            raise InjectedFault(f"injected after {step!r}")

    def _run(self, batches: list, stats: dict) -> None:
        try:
            for table, batch in batches:
                self.writer.write(table, batch)
            try:
                self.result = self.writer.commit(stats)
            except BaseException:
                self.writer.abort()
                raise
        except BaseException as exc:
            self.error = exc
        finally:
            self._stopped.put(None)

    def advance(self, order: str = "go") -> None:
        """Start, or go on from the step it stopped after (failing there if `order` is "fail"),
        up to its next step or its end."""
        if self.done:
            return
        if self._thread.is_alive():
            self._orders.put(order)
        else:
            self._thread.start()
        if self._stopped.get(timeout=300) is None:
            self.done = True
            self._thread.join()

    def run(self, steps: int) -> None:
        for _ in range(steps):
            self.advance()

    def finish(self) -> None:
        while not self.done:
            self.advance()


def below(store: Store, folder: str) -> Store:
    """The root `folder` below `store`'s, on the same connections (opening one per case
    would cost more than the case)."""
    where = f"/{folder}" if folder else ""
    return dataclasses.replace(store, uri=store.uri + where, root=store.root + where, _made=set())


#: Steps an attempt stops after in a commit: closed, one move per table, marked or lost.
COMMIT_STOPS = 5


def schedules() -> list[tuple[int, int, str]]:
    """(steps A takes, steps B then takes, which fails): A and B stop there, then the failing
    one (if any) fails at its stop and goes on to its abort's stop, the other finishes, then
    the first. B taking COMMIT_STOPS + 1 steps is B finishing."""
    out = []
    for a in range(1, COMMIT_STOPS + 1):
        for b in range(COMMIT_STOPS + 2):
            out += [(a, b, ""), (a, b, "A")]
            if 1 <= b <= COMMIT_STOPS:
                out.append((a, b, "B"))
    return out


@pytest.fixture(scope="module")
def shard_batches() -> tuple[Shard, list, dict]:
    """The first shard's record batches, in the order a generator writes them, and its stats."""
    shard = PLAN.shards()[0]
    batches: list = []
    stats = generate_shard(PLAN, shard, lambda table, batch: batches.append((table, batch)))
    return shard, batches, stats


def test_two_live_attempts_of_a_shard_commit_it_once_whatever_their_interleaving(
    root: str, shard_batches: tuple[Shard, list, dict], undisturbed: dict[str, pa.Table]
) -> None:
    shard, batches, stats = shard_batches
    want = first_shard_only(undisturbed)
    base = Store.open(root)
    for a_steps, b_steps, failing in schedules():
        store = below(base, f"a{a_steps}-b{b_steps}-{failing or 'none'}")
        # Each attempt its own Store (its own record of folders made), as on two machines.
        a = Attempt(below(store, ""), shard, batches, stats)
        b = Attempt(below(store, ""), shard, batches, stats)
        a.run(a_steps)
        b.run(b_steps)
        first, second = (b, a) if failing == "B" else (a, b)
        if failing:
            first.advance("fail")
            second.finish()
        first.finish()
        second.finish()
        case = f"A {a.steps}, B {b.steps}, failing {failing or 'none'}"
        markers = committed_shards(store)
        assert list(markers) == [shard.shard_id], case
        marker = markers[shard.shard_id]
        winner = a if marker["attempt"] == a.writer.attempt else b
        assert marker["attempt"] == winner.writer.attempt, case
        assert [a.writer.won, b.writer.won].count(True) == 1, case
        for attempt in (a, b):
            if failing and attempt is first:
                assert isinstance(attempt.error, InjectedFault), case
            else:
                assert attempt.error is None and attempt.result == marker, case
        # Each attempt cleaned up after itself: what is left is what the marker names.
        assert table_files(store) == sorted(marker["files"].values()), case
        assert_same(rows(store), want)
        assert_same(
            {t: plain_rows(store, t).sort_by("mechanism_id") for t in GENERATION_TABLES}, want
        )


def test_of_writers_racing_to_create_a_marker_exactly_one_wins(root: str) -> None:
    """The store's create-only write, on a folder and on SeaweedFS (If-None-Match)."""
    stores = [Store.open(root) for _ in range(2)]
    for round_ in range(3):
        relative = f"_links/shards/shard-{round_:06d}.json"
        start = threading.Barrier(8)

        def create(k: int, relative: str = relative, start: threading.Barrier = start) -> bool:
            start.wait()
            return stores[k % 2].create_exclusive(relative, b"writer %d" % k) is not None

        with ThreadPoolExecutor(8) as pool:
            won = list(pool.map(create, range(8)))
        assert won.count(True) == 1, won
        assert stores[0].read_bytes(relative) == b"writer %d" % won.index(True)
        assert stores[1].create_exclusive(relative, b"late") is None
        assert stores[0].read_bytes(relative) == b"writer %d" % won.index(True)


class Answering:
    """An HTTP server on 127.0.0.1 that answers every request with one fixed response: an S3
    endpoint that refuses, or ignores, conditional writes."""

    def __init__(self, status: int, body: bytes, headers: dict[str, str]) -> None:
        answer = (status, body, headers)

        class Handler(http.server.BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def do_PUT(self) -> None:
                self.rfile.read(int(self.headers.get("Content-Length", 0)))
                status, body, headers = answer
                self.send_response(status)
                for name, value in {**headers, "Content-Length": str(len(body))}.items():
                    self.send_header(name, value)
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args: object) -> None:
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.endpoint = f"http://127.0.0.1:{self.server.server_address[1]}"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    def __enter__(self) -> str:
        self.thread.start()
        return self.endpoint

    def __exit__(self, *exc: object) -> None:
        self.server.shutdown()
        self.server.server_close()


NOT_IMPLEMENTED = (
    b'<?xml version="1.0" encoding="UTF-8"?><Error><Code>NotImplemented</Code><Message>A header '
    b"you provided implies functionality that is not implemented</Message></Error>"
)


@pytest.mark.parametrize(
    "status, body, headers, message",
    [
        (
            501,
            NOT_IMPLEMENTED,
            {"Content-Type": "application/xml"},
            "refuses conditional writes (If-None-Match: NotImplemented)",
        ),
        (200, b"", {"ETag": '"0123456789abcdef"'}, "ignores If-None-Match"),
    ],
)
def test_an_s3_store_without_create_only_writes_is_refused_in_one_line(
    s3_env: str,
    monkeypatch: pytest.MonkeyPatch,
    status: int,
    body: bytes,
    headers: dict[str, str],
    message: str,
) -> None:
    store = Store.open(f"{s3_env}/data")  # SeaweedFS: opening checked that it honours the header
    shard = PLAN.shards()[0]
    writer = ShardWriter(store, shard.shard_id, shard.n_joints)
    stats = generate_shard(PLAN, shard, writer.write)
    with Answering(status, body, headers) as endpoint:
        # The conditional writes (boto3) now go to the answering server; the files (pyarrow)
        # still go to SeaweedFS.
        monkeypatch.setenv("AWS_ENDPOINT_URL", endpoint)
        store._client = None
        with pytest.raises(StoreError) as opening:
            store._probe_writes()
        if status != 200:  # a store that ignores the header lets a commit through: only
            with pytest.raises(StoreError) as committing:  # opening can tell
                try:
                    writer.commit(stats)
                except BaseException:
                    writer.abort()
                    raise
            assert str(committing.value) == str(opening.value)
        else:
            writer.abort()
        assert table_files(store) == []
    assert message in str(opening.value) and "\n" not in str(opening.value)
    assert str(opening.value).startswith(f"{s3_env}/data: ")


def test_a_local_commit_is_synced_before_it_is_marked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each file is synced before its move, the folders after the moves, and the marker before
    its link, its folder after: what the marker names is on the disk before the marker is."""
    store = Store.open(str(tmp_path / "data"))
    events: list[tuple[str, str]] = []
    fsync, link = os.fsync, os.link

    def spy_fsync(fd: int) -> None:
        events.append(("sync", os.readlink(f"/proc/self/fd/{fd}")))
        fsync(fd)

    def spy_link(source: str, target: str) -> None:
        link(source, target)
        events.append(("link", target))

    monkeypatch.setattr(os, "fsync", spy_fsync)
    monkeypatch.setattr(os, "link", spy_link)
    shard = PLAN.shards()[1]
    marker = write_shard(store, PLAN, shard, failpoint=lambda step: events.append(("step", step)))
    position = {event: k for k, event in enumerate(events)}
    marked = position[("link", store.path(marker_file(shard.shard_id)))]
    for table, relative in marker["files"].items():
        folder, name = store.path(relative).rsplit("/", 1)
        assert position[("sync", f"{folder}/_{name}")] < position[("step", "closed")], table
        moved = position[("step", f"moved {table}")]
        assert moved < max(k for k, e in enumerate(events) if e == ("sync", folder)) < marked
    synced = [e for e in events[:marked] if e[0] == "sync" and "_tmp-" in e[1]]
    assert synced and synced[-1][1].endswith(f"-shard-{shard.shard_id:06d}.json")
    assert ("sync", store.path("_links/shards")) in events[marked:]


@pytest.mark.parametrize("stops", range(1, COMMIT_STOPS))
def test_cleanup_beside_a_live_attempt_never_breaks_its_commit(
    root: str,
    stops: int,
    shard_batches: tuple[Shard, list, dict],
    undisturbed: dict[str, pa.Table],
) -> None:
    """Cleanup run while an attempt is between its steps (an actor a run gave up on, still
    writing): the attempt either commits whole or fails and leaves nothing."""
    shard, batches, stats = shard_batches
    store = Store.open(root)
    attempt = Attempt(below(store, ""), shard, batches, stats)
    attempt.run(stops)
    remove_uncommitted(store, "shards", committed_shards(store))
    attempt.finish()
    markers = committed_shards(store)
    if stops <= len(GENERATION_TABLES):  # hidden files of it were deleted: a move fails
        assert isinstance(attempt.error, OSError) and markers == {}
        assert table_files(store) == []
        return
    assert attempt.error is None and list(markers) == [shard.shard_id]
    assert table_files(store) == sorted(markers[shard.shard_id]["files"].values())
    assert_same(rows(store), first_shard_only(undisturbed))


def crafted_root(tmp_path: Path, named: str) -> tuple[Store, str]:
    """A root of two committed shards whose second marker names `named` for its mechanisms
    (OUTSIDE standing for the absolute path of `outside.parquet`), and beside the root a
    whole, readable copy of that shard's file there: had a reader followed the marker, it
    would have read rows. Returns the store and the file the marker named before."""
    store = Store.open(str(tmp_path / "data"))
    for shard in PLAN.shards()[:2]:
        write_shard(store, PLAN, shard)
    marker = json.loads(Path(store.path(marker_file(1))).read_text())
    own = marker["files"]["mechanisms"]
    outside = tmp_path / "outside.parquet"
    shutil.copy(store.path(own), outside)
    marker["files"]["mechanisms"] = named.replace("OUTSIDE", str(outside))
    Path(store.path(marker_file(1))).write_text(json.dumps(marker))
    return store, own


@pytest.mark.parametrize(
    ("named", "why"),
    [
        ("../outside.parquet", "a '..', '.' or empty part"),
        ("OUTSIDE", "an absolute path"),
        ("mechanisms/../../outside.parquet", "a '..', '.' or empty part"),
        ("file:OUTSIDE", "a scheme or drive"),
        ("s3://bucket/outside.parquet", "a scheme or drive"),
        ("mechanisms\\..\\..\\outside.parquet", "a backslash or NUL"),
        ("mechanisms/\0.parquet", "a backslash or NUL"),
        ("mechanisms//shard.parquet", "a '..', '.' or empty part"),
        ("escape/outside.parquet", "a path that resolves outside the root"),
    ],
    ids=["dotdot", "absolute", "inner-dotdot", "file", "s3", "backslash", "nul", "empty", "link"],
)
def test_a_marker_naming_a_file_outside_its_root_is_refused(
    tmp_path: Path, named: str, why: str
) -> None:
    """Every reader of markers meets the refusal: the marker reader, the readers of tables
    (`committed_files`, `open_table`, `load`), naming the marker and the path."""
    store, _ = crafted_root(tmp_path, named)
    (tmp_path / "data" / "escape").symlink_to(tmp_path)  # for "escape/...": a link out
    shown = repr(named.replace("OUTSIDE", str(tmp_path / "outside.parquet")))
    message = (
        f"{store.uri}: commit marker {marker_file(1)} names {shown}, {why}: a marker may name "
        "only files under its root"
    )
    for read in (
        lambda: committed_shards(store),
        lambda: committed_files(store, "simulations"),
        lambda: open_table(store, "mechanisms"),
        lambda: links_ray.load(store.uri, "mechanisms"),
    ):
        with pytest.raises(ValueError) as caught:
            read()
        assert str(caught.value) == message


def test_links_export_dataset_refuses_a_crafted_root_in_one_line(tmp_path: Path) -> None:
    """`links export-dataset` on a root whose marker names `../outside.parquet`: one line,
    exit status 2, nothing exported; the root itself exports once the marker is its own."""
    store, own = crafted_root(tmp_path, "../outside.parquet")
    result = links("export-dataset", store.uri, "--out", str(tmp_path / "export"))
    assert result.returncode == 2
    assert result.stderr.splitlines() == [
        f"links export-dataset: error: {store.uri}: commit marker {marker_file(1)} names "
        "'../outside.parquet', a '..', '.' or empty part: a marker may name only files under "
        "its root"
    ]
    assert not (tmp_path / "export").exists() or not any((tmp_path / "export").iterdir())
    marker = json.loads(Path(store.path(marker_file(1))).read_text())
    marker["files"]["mechanisms"] = own
    Path(store.path(marker_file(1))).write_text(json.dumps(marker))
    again = links("export-dataset", store.uri, "--out", str(tmp_path / "export"))
    assert again.returncode == 0, again.stderr
