"""One writer per root: a lease that a run holds while it writes, renews while it lives, and
that expires when it stops renewing.

A lease is a small file, ``ROOT/_links/leases/<name>.json``, naming its holder (what it is, its
host and process) and when it expires. It is taken and changed only by the store's conditional
writes (`Store.create_exclusive`, `replace_if`, `delete_if`), so of two runs racing for it exactly
one wins, and a run whose lease was taken over learns it at its next renewal.

- ``writer``: `links generate` and `links curate` hold it for the whole run. A second run on the
  same root is refused with a one-line message naming the holder.
- ``index``: the one process building the retrieval index cache; others wait for the cache, for a
  bounded time (`Lease.acquire_waiting`), then fail naming the holder.

A holder that dies stops renewing: its lease expires after `LEASE_TTL_S`, and at once if it ran
on this host and its process is gone. A held lease renews itself from a background thread every
quarter of its time to live; a run checks `Lease.confirm` before work that only the holder may
do (deleting what attempts left behind).
"""

from __future__ import annotations

import json
import os
import re
import socket
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import TypeVar

from links_ray.data.store import META, Store, StoreError

#: How long a lease lasts without renewal: far longer than a store's brief outages (a restart of
#: the S3 server takes seconds), short enough that a killed run's root is free within a minute.
LEASE_TTL_S = 60.0
#: Lease names, one per kind of exclusive work on a root; a part of a split retrieval index
#: has its own (`index_lease_name`), so the parts build at once.
LEASE_NAMES = ("writer", "index")


def index_lease_name(part: int, parts: int) -> str:
    """The lease of building part `part` of an index split in `parts`."""
    return "index" if parts == 1 else f"index-{part}-of-{parts}"


def _known_name(name: str) -> bool:
    return name in LEASE_NAMES or re.fullmatch(r"index-\d+-of-\d+", name) is not None


class LeaseHeld(StoreError):
    """Another live run holds the lease."""


class LeaseLost(StoreError):
    """This run's lease was taken over (it failed to renew in time)."""


Done = TypeVar("Done")


def lease_file(name: str) -> str:
    """The path, relative to the root, of lease `name`'s record."""
    return f"{META}/leases/{name}.json"


def _clock(seconds: float) -> str:
    return datetime.fromtimestamp(seconds, UTC).strftime("%H:%M:%S UTC")


def _holder(record: dict) -> str:
    """Who holds a lease, from its record: what, which process on which host, since when."""
    return (
        f"{record.get('holder', '?')} (pid {record.get('pid', '?')} on {record.get('host', '?')}, "
        f"since {_clock(record.get('acquired_at', 0))})"
    )


def _process_gone(record: dict) -> bool:
    """Whether the holder ran on this host and its process no longer exists."""
    if record.get("host") != socket.gethostname() or not isinstance(record.get("pid"), int):
        return False
    try:
        os.kill(record["pid"], 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # alive, someone else's
        return False
    return False


@dataclass
class Lease:
    """A held lease; use as a context manager to renew it while the block runs."""

    store: Store
    name: str
    record: dict
    version: str
    lost: bool = False
    _stop: threading.Event = field(default_factory=threading.Event, repr=False)
    _thread: threading.Thread | None = field(default=None, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def token(self) -> str:
        """This holder's token: the lease is this run's while the record carries it."""
        return self.record["token"]

    @classmethod
    def try_acquire(
        cls, store: Store, name: str, holder: str, ttl_s: float = LEASE_TTL_S
    ) -> Lease | dict:
        """The lease, or the record of the live holder that has it."""
        if not _known_name(name):
            raise ValueError(f"lease name must be one of {', '.join(LEASE_NAMES)}, got {name!r}")
        if not ttl_s > 0:
            raise ValueError(f"ttl_s must be positive, got {ttl_s!r}")
        relative = lease_file(name)
        for _ in range(5):  # each turn loses only to a run that changed the lease meanwhile
            record = _new_record(holder, ttl_s)
            encoded = _encode(record)
            created = store.create_exclusive(relative, encoded)
            if created is not None:
                return cls(store, name, record, created)
            found = store.read_versioned(relative)
            if found is None:
                continue  # released between our two requests
            data, version = found
            try:
                current = json.loads(data)
                expired = current["expires_at"] < time.time() or _process_gone(current)
            except (ValueError, KeyError, TypeError):  # unreadable: nobody can be holding it
                current, expired = {}, True
            if not expired:
                return current
            taken = store.replace_if(relative, version, encoded)
            if taken is not None:
                return cls(store, name, record, taken)
        raise LeaseHeld(f"{store.uri}: the {name} lease keeps changing hands; try again")

    @classmethod
    def acquire(cls, store: Store, name: str, holder: str, ttl_s: float = LEASE_TTL_S) -> Lease:
        """The lease, or `LeaseHeld` naming the live holder."""
        got = cls.try_acquire(store, name, holder, ttl_s)
        if isinstance(got, Lease):
            return got
        raise LeaseHeld(
            f"{store.uri} is in use by {_holder(got)}; wait for it to finish, or stop it: its "
            f"lease lapses {got.get('ttl_s', LEASE_TTL_S):.0f} s after it stops renewing"
        )

    @classmethod
    def acquire_waiting(
        cls,
        store: Store,
        name: str,
        holder: str,
        wait_s: float,
        done: Callable[[], Done | None],
        ttl_s: float = LEASE_TTL_S,
        poll_s: float = 1.0,
    ) -> Lease | Done:
        """The lease, once its holder gives it up, or what `done` returns (not None) first:
        the holder's work, finished. `LeaseHeld` after `wait_s` seconds, naming the holder and
        the wait."""
        if not wait_s >= 0:
            raise ValueError(f"wait_s must be zero or more, got {wait_s!r}")
        if not poll_s > 0:
            raise ValueError(f"poll_s must be positive, got {poll_s!r}")
        start = time.monotonic()
        while True:
            got = cls.try_acquire(store, name, holder, ttl_s)
            if isinstance(got, Lease):
                return got
            waited = time.monotonic() - start
            if waited >= wait_s:
                raise LeaseHeld(
                    f"{store.uri}: gave up on the {name} lease after waiting {waited:.0f} s "
                    f"(wait_s={wait_s:g}): it is held by {_holder(got)}"
                )
            time.sleep(min(poll_s, wait_s - waited))
            finished = done()
            if finished is not None:
                return finished

    def renew(self) -> bool:
        """Extend the lease; False (and `lost`) if another run took it over."""
        with self._lock:
            if self.lost:
                return False
            record = {**self.record, "expires_at": time.time() + self.record["ttl_s"]}
            version = self.store.replace_if(lease_file(self.name), self.version, _encode(record))
            if version is None:
                self.lost = True
                return False
            self.record, self.version = record, version
            return True

    def confirm(self) -> None:
        """Renew now, or raise `LeaseLost`: the fence before work only the holder may do."""
        if not self.renew():
            raise LeaseLost(
                f"{self.store.uri}: this run's {self.name} lease was taken over by another run "
                "(it could not be renewed in time); stopping"
            )

    def release(self) -> None:
        """Stop renewing and give the lease up (if it is still ours)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        with self._lock:
            if not self.lost:
                self.store.delete_if(lease_file(self.name), self.version)
                self.lost = True

    def _renew_until_stopped(self) -> None:
        while not self._stop.wait(self.record["ttl_s"] / 4):
            try:
                if not self.renew():
                    return
            except (OSError, StoreError):  # the store is away: try again next time
                continue

    def keep_renewed(self) -> Lease:
        """Renew the lease from a background thread until `release`."""
        if self._thread is None:
            self._thread = threading.Thread(
                target=self._renew_until_stopped, name=f"lease-{self.name}", daemon=True
            )
            self._thread.start()
        return self

    def __enter__(self) -> Lease:
        return self.keep_renewed()

    def __exit__(self, *_: object) -> None:
        try:
            self.release()
        except (OSError, StoreError):  # the lease lapses on its own
            pass


def holder_still(store: Store, name: str, token: str) -> bool:
    """Whether the lease `name` is held by `token` (for a run's workers, which hold no Lease)."""
    found = store.read_versioned(lease_file(name))
    return found is not None and _token(found[0]) == token


def _token(data: bytes) -> str | None:
    try:
        return json.loads(data).get("token")
    except (ValueError, AttributeError):
        return None


def _new_record(holder: str, ttl_s: float) -> dict:
    now = time.time()
    return {
        "holder": holder,
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "token": uuid.uuid4().hex,
        "acquired_at": now,
        "expires_at": now + ttl_s,
        "ttl_s": ttl_s,
    }


def _encode(record: dict) -> bytes:
    return (json.dumps(record, indent=1) + "\n").encode()
