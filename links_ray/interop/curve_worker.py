"""Untrusted drawing files read in reader processes, where a runaway parse cannot stop the caller.

`read_curve_isolated(name, data, part, points)` reads a file's contents as `read_curve_text`
does, in one of CURVE_READERS long-lived reader processes. Each reader is a fresh interpreter
(started by exec, never a fork of the caller, a server whose threads a fork would copy
mid-flight), at CURVE_READER_NICENESS, with one numpy thread, its address space limited to
CURVE_READER_MEMORY_BYTES
and each file to CURVE_READ_SECONDS: a reader that overruns is killed (SIGKILL) and a new one
started for the next file; one that dies is replaced the same way. The caller waits on a pipe,
without the GIL, and a file that finds every reader busy for CURVE_READER_WAIT_S is turned away.

What the caller may meet, with the HTTP status each stands for:

- `ValueError`: the file's problem, named with the file, as `read_curve_text` says it: 400;
- `CurveFileTooLarge` (a ValueError): the file is past a limit on its size or on what it holds
  (`limit` names it: MAX_SVG_ELEMENTS, MAX_CURVE_SEGMENTS, ...): 413;
- `CurveFileTooCostly` (a ValueError): reading it overran the reader's time or memory, or
  crashed it (`limit`: CURVE_READ_SECONDS or CURVE_READER_MEMORY_BYTES): 422;
- `CurveReadersBusy` (a RuntimeError): no reader was free within CURVE_READER_WAIT_S: 503;
- any other RuntimeError: a reader that could not start or answered nonsense: 500.

Each of the first three carries `status`, its HTTP status. The readers need no Ray: this
module runs as well under the CLI, a test or a Serve replica.
"""

from __future__ import annotations

import atexit
import os
import resource
import signal
import socket
import struct
import subprocess
import sys
import threading
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np
import orjson

from links_ray.engine.inputs import MAX_POINTS, MIN_POINTS, as_drawn_points, as_int
from links_ray.interop.curve_files import (
    DEFAULT_CURVE_POINTS,
    Curve,
    curve_file_bytes,
    read_curve_text,
)
from links_ray.interop.curve_limits import (
    CURVE_READ_SECONDS,
    CURVE_READER_MEMORY_BYTES,
    CURVE_READER_NICENESS,
    CURVE_READER_WAIT_S,
    CURVE_READERS,
    MAX_CURVE_FILE_BYTES,
)
from links_ray.interop.outlines import CurveFileTooLarge

__all__ = [
    "CurveFileTooCostly",
    "CurveReaders",
    "CurveReadersBusy",
    "read_curve_isolated",
    "warm_curve_readers",
]

#: Seconds a reader is given to start (import numpy, numba, svgelements and ezdxf): generous,
#: since a loaded machine starts a process slowly, and a reader starts once.
START_SECONDS = 60.0
#: Threads a reader's numerical libraries may start: one, so that its address space holds one
#: thread's buffers.
_ONE_THREAD = {
    name: "1"
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")
}
_READY = b"ready"
#: The longest request header (a file's name, its part, the points): names far longer than
#: any the HTTP API takes.
_HEADER_BYTES = 1024 * 1024


class CurveFileTooCostly(ValueError):
    """Reading a file overran its reader's time (`limit` "CURVE_READ_SECONDS") or memory
    ("CURVE_READER_MEMORY_BYTES"), or crashed the reader (counted as memory: what crashes
    one under its limit is an allocation that failed). The HTTP API answers it with 422."""

    status = 422

    def __init__(self, message: str, limit: str) -> None:
        super().__init__(message)
        self.limit = limit


class CurveReadersBusy(RuntimeError):
    """Every reader stayed busy for CURVE_READER_WAIT_S: the caller may try again later. The
    HTTP API answers it with 503."""

    status = 503


def read_curve_isolated(
    name: str, data: str | bytes, part: str | None = None, points: int = DEFAULT_CURVE_POINTS
) -> Curve:
    """The curve in a file's contents `data`, as `read_curve_text(name, data, part, points)`
    reads it, read in a reader process of the process's own `CurveReaders` (started on first
    use, closed at exit). Raises what the module's docstring lists."""
    return _shared().read(name, data, part, points)


def warm_curve_readers() -> None:
    """Start the process's own readers now (`CurveReaders.warm`): a server calls it when it
    starts, so that its first drawings wait for no reader to start."""
    _shared().warm()


class CurveReaders:
    """At most `readers` reader processes, each reading one file at a time within `seconds`
    and `memory_bytes` of address space; a caller waits at most `wait_s` for one. Readers
    start when first needed (or at `warm`) and live until `close`. Thread-safe."""

    def __init__(
        self,
        readers: int = CURVE_READERS,
        seconds: float = CURVE_READ_SECONDS,
        memory_bytes: int = CURVE_READER_MEMORY_BYTES,
        wait_s: float = CURVE_READER_WAIT_S,
    ) -> None:
        self.readers = as_int("readers", readers, 1)
        self.seconds = float(seconds)
        self.memory_bytes = as_int("memory_bytes", memory_bytes, 1)
        self.wait_s = float(wait_s)
        self._slots = threading.BoundedSemaphore(self.readers)
        self._lock = threading.Lock()
        self._idle: list[_Reader] = []
        self._reading: set[_Reader] = set()
        self._closed = False

    def read(
        self,
        name: str,
        data: str | bytes,
        part: str | None = None,
        points: int = DEFAULT_CURVE_POINTS,
    ) -> Curve:
        """The curve in `data`, the contents of the file `name`, read in a reader: see the
        module's docstring for what it raises."""
        count = as_int("points", points, MIN_POINTS, MAX_POINTS)
        data = curve_file_bytes(name, data)  # a file too large refused here, not sent
        request = orjson.dumps({"name": name, "part": part, "points": count})
        if len(request) > _HEADER_BYTES:
            raise ValueError(f"a file's name and id may take {_HEADER_BYTES:,} bytes at most")
        if not self._slots.acquire(timeout=self.wait_s):
            raise CurveReadersBusy(
                f"{name}: no curve reader came free within {self.wait_s:g} s (all "
                f"{self.readers} busy): try again"
            )
        try:
            reader = self._take()
            try:
                header, body = reader.ask(request, data)
            except _Lost as lost:
                self._discard(reader)
                raise self._costly(name, lost) from None
            except BaseException:
                self._discard(reader)
                raise
            # One whose allocation failed exits, wherever in it that was.
            healthy = header.get("error") != "memory"
            try:
                return _answer(name, header, body, count, self.memory_bytes)
            except RuntimeError:  # a bug's answer, or nonsense: the next file gets a new one
                healthy = False
                raise
            finally:
                (self._give_back if healthy else self._discard)(reader)
        finally:
            self._slots.release()

    def warm(self) -> None:
        """Start every reader now, so that the first files wait for none to start."""
        started = []
        for _ in range(self.readers):
            if not self._slots.acquire(timeout=self.wait_s):
                break
            try:
                started.append(self._take())
            except BaseException:
                self._slots.release()
                raise
        for reader in started:
            self._give_back(reader)
            self._slots.release()

    def reading(self) -> int:
        """How many files are being read now."""
        with self._lock:
            return len(self._reading)

    def pids(self) -> list[int]:
        """The process ids of the readers running, idle or reading."""
        with self._lock:
            return sorted(reader.process.pid for reader in [*self._idle, *self._reading])

    def close(self) -> None:
        """Stop every reader; a file being read is answered first. Reads after this fail."""
        with self._lock:
            self._closed = True
            idle, self._idle = self._idle, []
        for reader in idle:
            reader.stop()

    def __enter__(self) -> CurveReaders:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def _take(self) -> _Reader:
        """An idle reader that is alive, or a new one (the caller holds a slot)."""
        with self._lock:
            if self._closed:
                raise RuntimeError("the curve readers are closed")
            while self._idle:
                reader = self._idle.pop()
                if reader.process.poll() is None:
                    self._reading.add(reader)
                    return reader
                reader.stop()  # it died idle: not the next file's fault
        reader = _Reader(self.seconds, self.memory_bytes)
        with self._lock:
            self._reading.add(reader)
        return reader

    def _give_back(self, reader: _Reader) -> None:
        with self._lock:
            self._reading.discard(reader)
            if not self._closed:
                self._idle.append(reader)
                return
        reader.stop()

    def _discard(self, reader: _Reader) -> None:
        with self._lock:
            self._reading.discard(reader)
        reader.stop()

    def _costly(self, name: str, lost: _Lost) -> CurveFileTooCostly:
        if lost.timed_out:
            return CurveFileTooCostly(
                f"{name}: reading it took longer than {self.seconds:g} s, the most a curve "
                "file is given",
                "CURVE_READ_SECONDS",
            )
        return CurveFileTooCostly(
            f"{name}: reading it stopped its reader ({lost.how}), most likely past the "
            f"{_mib(self.memory_bytes)} of memory a reader is given",
            "CURVE_READER_MEMORY_BYTES",
        )


# -- the caller's side of one reader ----------------------------------------------------------


class _Lost(Exception):
    """A reader that overran its time (`timed_out`) or died (`how`)."""

    def __init__(self, timed_out: bool, how: str = "") -> None:
        super().__init__(how or "timed out")
        self.timed_out = timed_out
        self.how = how


class _Reader:
    """A reader process and the caller's end of its socket."""

    def __init__(self, seconds: float, memory_bytes: int) -> None:
        self.seconds = seconds
        ours, theirs = socket.socketpair()
        # A reader that stops reading or answering mid-message stalls no call past this.
        stall = struct.pack("ll", int(seconds) + 1, 0)
        ours.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, stall)
        ours.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, stall)
        package = Path(__file__).resolve().parents[1]
        arguments = (package, theirs.fileno(), memory_bytes, seconds)
        try:
            self.process = subprocess.Popen(
                # -P: no current directory on its path, whatever the caller's is.
                [sys.executable, "-P", "-c", _BOOT, *map(str, arguments)],
                pass_fds=[theirs.fileno()],
                env={**os.environ, **_ONE_THREAD},
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                start_new_session=True,  # a terminal's Ctrl-C is the caller's to handle
            )
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        self.connection = Connection(ours.detach())
        try:
            ready = self.connection.poll(START_SECONDS) and self.connection.recv_bytes(64)
        except (EOFError, OSError):
            ready = b""
        if ready != _READY:
            self.stop()
            raise RuntimeError(
                f"a curve reader did not start within {START_SECONDS:g} s "
                f"({self._ended() or 'no answer'})"
            )

    def ask(self, header: bytes, data: bytes) -> tuple[dict, bytes]:
        """The reader's answer to a file: its header and body, or `_Lost`."""
        try:
            self.connection.send_bytes(header)
            self.connection.send_bytes(data)
            if not self.connection.poll(self.seconds):
                raise _Lost(timed_out=True)
            answer = self.connection.recv_bytes(4 * _HEADER_BYTES)  # a message names the file
            body = self.connection.recv_bytes(16 * MAX_POINTS)
        except (EOFError, OSError):  # it died, or stalled mid-message
            self.process.kill()
            raise _Lost(timed_out=False, how=self._ended() or "its pipe broke") from None
        try:
            header_read = orjson.loads(answer)
        except orjson.JSONDecodeError:
            header_read = None
        if not isinstance(header_read, dict):
            raise RuntimeError("a curve reader answered what is not an answer")
        return header_read, body

    def stop(self) -> None:
        """Kill the process (SIGKILL: whatever it is doing) and reap it."""
        self.connection.close()
        self.process.kill()
        self.process.wait()

    def _ended(self) -> str:
        """How the process ended, if it has ("killed by SIGSEGV", "exit status 1")."""
        try:
            code = self.process.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            return ""
        if code < 0:
            return f"killed by {signal.Signals(-code).name}"
        return f"exit status {code}"


def _answer(name: str, header: dict, body: bytes, count: int, memory_bytes: int) -> Curve:
    """The curve a reader answered, checked as if read here, or the exception it raised."""
    error = header.get("error")
    message = header.get("message")
    if error is not None:
        if not isinstance(message, str):
            raise RuntimeError("a curve reader answered an error without its message")
        if error == "value":
            raise ValueError(message)
        if error == "too_large":
            raise CurveFileTooLarge(message, str(header.get("limit")))
        if error == "memory":
            raise CurveFileTooCostly(
                f"{name}: reading it took more than the {_mib(memory_bytes)} of memory a "
                "reader is given",
                "CURVE_READER_MEMORY_BYTES",
            )
        raise RuntimeError(f"a curve reader failed reading {name}: {message}")
    closed, source = header.get("closed"), header.get("source")
    if not isinstance(closed, bool) or not isinstance(source, str) or len(body) != 16 * count:
        raise RuntimeError(f"a curve reader answered nonsense for {name}")
    points = np.frombuffer(body, dtype=np.float64).reshape(count, 2).copy()
    return Curve(as_drawn_points(points, "the curve's points"), closed, source)


def _mib(size: int) -> str:
    return f"{size / 2**20:,.0f} MiB"


# -- the reader's side ------------------------------------------------------------------------

#: What a reader runs: links_ray entered without its own __init__, which loads the compiled
#: kernels and pyarrow (about 1.2 GB of address space the limit would count, for nothing
#: the reader uses).
_BOOT = """
import sys, types
package = types.ModuleType("links_ray")
package.__path__ = [sys.argv[1]]
sys.modules["links_ray"] = package
from links_ray.interop.curve_worker import _serve
_serve(int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]))
"""


def _serve(handle: int, memory_bytes: int, seconds: float) -> None:
    """A reader's life: at CURVE_READER_NICENESS, its libraries loaded, its address space
    limited to `memory_bytes`, files read one at a time from the socket `handle` until the
    caller closes it. Each file is given CPU time for twice `seconds` (and 2 s) too: a reader
    the caller no longer watches stops itself."""
    _lower_priority()
    import ezdxf  # noqa: F401 - loaded before the limit, as every file needs
    import svgelements  # noqa: F401

    _limit(resource.RLIMIT_AS, memory_bytes)
    _limit(resource.RLIMIT_CORE, 0)  # a crash leaves no core file behind
    connection = Connection(handle)
    connection.send_bytes(_READY)
    while True:
        try:
            request = orjson.loads(connection.recv_bytes(_HEADER_BYTES))
            data = connection.recv_bytes(MAX_CURVE_FILE_BYTES)
        except EOFError:
            return
        usage = resource.getrusage(resource.RUSAGE_SELF)
        _limit(resource.RLIMIT_CPU, int(usage.ru_utime + usage.ru_stime + 2 * seconds) + 2)
        header, body = _read(request, data)
        connection.send_bytes(orjson.dumps(header))
        connection.send_bytes(body)
        if header.get("error") == "memory":
            return


def _lower_priority() -> None:
    """This process at CURVE_READER_NICENESS, unless it runs lower already. Set before any
    thread starts: Linux keeps a niceness per thread, and new threads inherit it."""
    current = os.getpriority(os.PRIO_PROCESS, 0)
    if current < CURVE_READER_NICENESS:
        os.setpriority(os.PRIO_PROCESS, 0, CURVE_READER_NICENESS)


def _limit(which: int, soft: int) -> None:
    """Set the soft limit `which` to `soft`, or to the hard limit if that is lower."""
    _, hard = resource.getrlimit(which)
    if hard != resource.RLIM_INFINITY:
        soft = min(soft, hard)
    resource.setrlimit(which, (soft, hard))


def _read(request: dict, data: bytes) -> tuple[dict, bytes]:
    """A reader's answer to one file: a header and the points' bytes."""
    try:
        curve = read_curve_text(request["name"], data, request["part"], request["points"])
    except MemoryError:
        return {"error": "memory", "message": "out of memory"}, b""
    except CurveFileTooLarge as exc:
        return {"error": "too_large", "message": str(exc), "limit": exc.limit}, b""
    except ValueError as exc:
        return {"error": "value", "message": str(exc)}, b""
    except Exception as exc:  # a bug: said to the caller, which raises it
        return {"error": "failed", "message": f"{type(exc).__name__}: {exc}"}, b""
    header = {"closed": curve.closed, "source": curve.source}
    return header, np.ascontiguousarray(curve.points, dtype=np.float64).tobytes()


_shared_readers: tuple[int, CurveReaders] | None = None
_shared_lock = threading.Lock()


def _shared() -> CurveReaders:
    """The process's own readers, made on first use and closed at exit (a forked copy of the
    process makes its own: the readers answer the process that started them)."""
    global _shared_readers
    with _shared_lock:
        if _shared_readers is None or _shared_readers[0] != os.getpid():
            readers = CurveReaders()
            atexit.register(readers.close)
            _shared_readers = (os.getpid(), readers)
        return _shared_readers[1]
