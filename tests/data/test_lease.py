"""One writer per root: the lease, on a local folder and on the SeaweedFS S3 server.

Real processes hold and lose leases here: racing threads, a holder killed by SIGKILL, a holder
that stops renewing.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

import links_ray
from links_ray.data.lease import Lease, LeaseHeld, LeaseLost, holder_still, lease_file
from links_ray.data.store import Store


@pytest.fixture(params=["local", "s3"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Store:
    if request.param == "local":
        return Store.open(str(tmp_path / "data"))
    return Store.open(f"{request.getfixturevalue('s3_env')}/data")


def test_a_second_holder_is_refused_with_the_holders_name(store: Store) -> None:
    with Lease.acquire(store, "writer", "links generate") as held:
        assert holder_still(store, "writer", held.token)
        with pytest.raises(LeaseHeld) as refused:
            Lease.acquire(store, "writer", "links curate")
        message = str(refused.value)
        assert "\n" not in message
        assert f"in use by links generate (pid {os.getpid()} on {socket.gethostname()}" in message
        # Another kind of lease is another lock.
        Lease.acquire(store, "index", "an index build").release()
    # Released: the next run takes it at once.
    Lease.acquire(store, "writer", "links curate").release()


def test_racing_runs_get_exactly_one_lease(store: Store) -> None:
    barrier = threading.Barrier(8)
    won: list[Lease] = []

    def contend() -> None:
        barrier.wait()
        got = Lease.try_acquire(store, "writer", "a racer")
        if isinstance(got, Lease):
            won.append(got)

    racers = [threading.Thread(target=contend) for _ in range(8)]
    for racer in racers:
        racer.start()
    for racer in racers:
        racer.join()
    assert len(won) == 1
    assert holder_still(store, "writer", won[0].token)


def test_a_lease_nobody_renews_lapses_and_its_holder_learns_it(store: Store) -> None:
    stalled = Lease.acquire(store, "writer", "a stalled run", ttl_s=1.0)  # never renewed
    with pytest.raises(LeaseHeld):
        Lease.acquire(store, "writer", "the next run")
    time.sleep(1.2)
    with Lease.acquire(store, "writer", "the next run") as taken:
        assert holder_still(store, "writer", taken.token)
        assert not stalled.renew() and stalled.lost
        with pytest.raises(LeaseLost, match="taken over by another run"):
            stalled.confirm()
        stalled.release()  # must not give away the new holder's lease
        assert holder_still(store, "writer", taken.token)


def test_a_held_lease_renews_itself(store: Store) -> None:
    with Lease.acquire(store, "writer", "a long run", ttl_s=1.0) as held:
        time.sleep(2.5)
        with pytest.raises(LeaseHeld):
            Lease.acquire(store, "writer", "the next run")
        held.confirm()


HOLDER = textwrap.dedent(
    """
    import sys, time
    from links_ray.data.lease import Lease
    from links_ray.data.store import Store

    lease = Lease.acquire(Store.open(sys.argv[1]), "writer", "a doomed run")
    print("held", flush=True)
    time.sleep(600)
    """
)


def test_a_killed_holders_lease_is_free_at_once_on_its_host(tmp_path: Path) -> None:
    root = str(tmp_path / "data")
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER, root],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(Path(links_ray.__file__).parents[1])},
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(LeaseHeld, match=f"pid {holder.pid} "):
            Lease.acquire(Store.open(root), "writer", "the next run")
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    # Its lease would last a minute more, but its process is gone.
    Lease.acquire(Store.open(root), "writer", "the next run").release()


def test_an_unreadable_lease_is_free(store: Store) -> None:
    store.write_bytes(lease_file("writer"), b'{"holder": "half a rec')
    Lease.acquire(store, "writer", "the next run").release()


def test_bad_lease_arguments_are_named(store: Store) -> None:
    with pytest.raises(ValueError, match="lease name must be one of writer, index"):
        Lease.acquire(store, "reader", "x")
    with pytest.raises(ValueError, match="ttl_s must be positive"):
        Lease.acquire(store, "writer", "x", ttl_s=0)


INDEX_HOLDER = textwrap.dedent(
    """
    import sys
    from links_ray.data.lease import Lease
    from links_ray.data.store import Store

    with Lease.acquire(Store.open(sys.argv[1]), "index", "a replica building the index"):
        print("held", flush=True)
        sys.stdin.readline()  # until told to finish
    print("released", flush=True)
    """
)


def hold_index_lease(uri: str) -> subprocess.Popen[str]:
    """Another process holding (and renewing) `uri`'s index lease until a line on its stdin."""
    holder = subprocess.Popen(
        [sys.executable, "-c", INDEX_HOLDER, uri],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(Path(links_ray.__file__).parents[1])},
    )
    assert holder.stdout.readline().strip() == "held"
    return holder


def finish(holder: subprocess.Popen[str]) -> None:
    holder.stdin.write("done\n")
    holder.stdin.flush()
    assert holder.stdout.readline().strip() == "released"
    assert holder.wait(timeout=60) == 0


def test_a_waiter_gives_up_after_its_bound_naming_the_holder(store: Store) -> None:
    holder = hold_index_lease(store.uri)
    try:
        start = time.monotonic()
        with pytest.raises(LeaseHeld) as refused:
            Lease.acquire_waiting(store, "index", "a waiter", 2.0, done=lambda: None, poll_s=0.2)
        assert time.monotonic() - start >= 2.0
        message = str(refused.value)
        assert "\n" not in message
        assert message.startswith(
            f"{store.uri}: gave up on the index lease after waiting 2 s (wait_s=2): it is held "
            f"by a replica building the index (pid {holder.pid} on {socket.gethostname()}, since "
        ), message

        # What the waiter waits for (the holder's work, done) ends the wait.
        polls: list[int] = []

        def built() -> str | None:
            polls.append(1)
            return "built" if len(polls) == 3 else None

        got = Lease.acquire_waiting(store, "index", "a waiter", 60.0, done=built, poll_s=0.2)
        assert got == "built" and len(polls) == 3
        assert isinstance(Lease.try_acquire(store, "index", "a waiter"), dict)  # still held
    finally:
        finish(holder)
    # Given up by its holder, the lease goes to the waiter.
    got = Lease.acquire_waiting(store, "index", "a waiter", 60.0, done=lambda: None)
    assert isinstance(got, Lease) and holder_still(store, "index", got.token)
    got.release()


def test_bad_wait_arguments_are_named(store: Store) -> None:
    with pytest.raises(ValueError, match="wait_s must be zero or more, got -1"):
        Lease.acquire_waiting(store, "index", "x", -1, done=lambda: None)
    with pytest.raises(ValueError, match="poll_s must be positive, got 0"):
        Lease.acquire_waiting(store, "index", "x", 1, done=lambda: None, poll_s=0)
