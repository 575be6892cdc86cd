"""Building and launching the Ray Serve application behind `links serve`: the HTTP API of
docs/reference/contract.md and the web studio.

`build_app` makes the application of a dataset (one index in the gateway, `LinksApi`, or the
index split into `IndexPartition` deployments: `serve.deployments`), and `app_builder` does the
same for Serve config files (deploy/serve/serve_config.yaml), whose `shards` arg, like `links
serve --shards N`, is the number of partitions. The app the gateway answers with is
`serve.http.asgi`'s, its routes `serve.http.routes`'.

`run_server` (what `links serve` runs) starts its own Ray and puts the request gate
(`serve.http.gate`) on the address asked for: it reads each request whole, under the bounds of
`serve.http.limits`, and only then passes it to Serve on loopback, so that slow or idle clients hold
none of Serve's places. With one replica (the gateway, with partitions), the replica answers
the gate itself: Ray Serve's *direct ingress*, which spares every request the actor hop to
Serve's HTTP proxy and a second one to fetch the body. With several replicas, the proxy
answers the gate and balances them. On a cluster that Ray was already running, the proxy
answers on the address asked for, and the cluster's own ingress stands in front of it.
On Ctrl-C or SIGTERM it stops in bounded time
(`stop_serving`): the replicas drain the requests under way for at most `SHUTDOWN_DRAIN_S`,
then Serve and the Ray it started stop.
"""

import gc
import logging
import math
import os
import random
import signal
import socket
import sys
import time
from pathlib import Path
from typing import Any

from ray import serve
from ray.serve.deployment import Application

from links_ray.data.commit import committed_shards
from links_ray.data.dataset import open_table
from links_ray.data.store import Store
from links_ray.serve.deployments import REPLICA_ENV, SHUTDOWN_DRAIN_S, IndexPartition, LinksApi
from links_ray.serve.http.gate import GateThread, RequestGate
from links_ray.serve.http.limits import MAX_RETRIEVALS, PARTITION_TIMEOUT_S
from links_ray.serve.http.middleware import as_host_names

#: CPUs a partition replica reserves unless told otherwise (`--shard-cpus`, and unless
#: `fit_partition_cpus` gives it less on a Ray that `links serve` started itself); Ray counts
#: CPUs in steps of 1 / CPU_STEPS.
PARTITION_CPUS, CPU_STEPS = 1.0, 10_000
#: Where Serve's HTTP servers listen when `links serve` puts its request gate before them.
LOOPBACK = "127.0.0.1"
#: Seconds `links serve` gives Serve's controller beyond the drain to stop the replicas and
#: proxies, before it stops Ray under them.
SHUTDOWN_STOP_S = 5.0


def check_root(root: str, shards: int | None = None) -> None:
    """Fail early, with ValueError naming the problem, if `root` has no curated table, or has
    a partition without curated shards when the index is split into `shards` partitions."""
    store = Store.open(root, writable=False)
    open_table(store, "curated")
    if shards:
        numbers = [
            shard
            for shard, marker in committed_shards(store, "curation").items()
            if "curated" in marker["files"]
        ]
        empty = sorted(set(range(shards)) - {shard % shards for shard in numbers})
        if empty:
            raise ValueError(
                f"{store.uri} has {len(numbers)} curated shards: split in {shards} partitions, "
                f"partition {empty[0]} would have none; use a smaller --shards"
            )


def _positive(name: str, value: object, kind: type = int) -> Any:
    """`value` if it is a positive integer (`kind` int) or a positive finite number (`kind`
    float, which takes integers too), else ValueError naming `name`."""
    accepted = (int, float) if kind is float else (int,)
    if (
        isinstance(value, bool)
        or not isinstance(value, accepted)
        or not (value > 0 and math.isfinite(value))
    ):
        what = "integer" if kind is int else "number"
        raise ValueError(f"{name} must be a positive {what}, got {value!r}")
    return value


def build_app(
    root: str,
    replicas: int = 1,
    shards: int | None = None,
    shard_cpus: float = PARTITION_CPUS,
    shard_memory_gb: float | None = None,
    max_retrievals: int = MAX_RETRIEVALS,
    partition_timeout_s: float = PARTITION_TIMEOUT_S,
    allowed_hosts: tuple[str, ...] | list[str] = (),
) -> Application:
    """The Serve application for dataset `root` (not yet running), answering requests for
    its addresses, `localhost` and the host names `allowed_hosts` (`*`: any).

    Without `shards`, `replicas` replicas of `LinksApi`, each holding the whole index. With
    `shards` = N, the index split into N partitions: N `IndexPartition` deployments
    (`IndexPartition-P-of-N`), each of `replicas` replicas holding partition P, with
    `shard_cpus` CPUs and `shard_memory_gb` GB of memory reserved in Ray per replica, placed
    wherever the cluster has room; and `replicas` replicas of the gateway, `LinksApi`, which
    asks them all. (`shards` and its kin keep the names of `links serve`'s flags.)
    """
    _positive("replicas", replicas)
    _positive("max_retrievals", max_retrievals)
    _positive("partition_timeout_s", partition_timeout_s, float)
    gateway_args = {
        "max_retrievals": max_retrievals,
        "partition_timeout_s": partition_timeout_s,
        "allowed_hosts": tuple(sorted(as_host_names(allowed_hosts))),
    }
    gateway = LinksApi.options(num_replicas=replicas)
    if shards is None:
        return gateway.bind(root, **gateway_args)
    _positive("shards", shards)
    options: dict[str, Any] = {
        "num_cpus": _positive("shard_cpus", shard_cpus, float),
        "runtime_env": {"env_vars": REPLICA_ENV},
    }
    if shard_memory_gb is not None:
        options["memory"] = round(_positive("shard_memory_gb", shard_memory_gb, float) * 1e9)
    partitions = [
        IndexPartition.options(
            name=f"IndexPartition-{part}-of-{shards}",
            num_replicas=replicas,
            ray_actor_options=options,
        ).bind(root, part, shards)
        for part in range(shards)
    ]
    return gateway.bind(root, partitions, **gateway_args)


#: The args of the Serve config application (`app_builder`), and how each is read.
APP_ARGS = {
    "root": str,
    "replicas": int,
    "shards": int,
    "shard_cpus": float,
    "shard_memory_gb": float,
    "max_retrievals": int,
    "allowed_hosts": list,
}


def _arg(args: dict[str, Any], name: str) -> Any:
    """Config arg `name`, checked as its type in APP_ARGS (`serve run ... replicas=2` passes
    strings, which are read as numbers first)."""
    value, kind = args[name], APP_ARGS[name]
    if isinstance(value, str):
        try:
            value = kind(value.strip())
        except ValueError:
            pass
    try:
        return _positive(name, value, kind)
    except ValueError:
        what = "integer" if kind is int else "number"
        raise ValueError(f"args.{name} must be a positive {what}, got {args[name]!r}") from None


def app_builder(args: dict[str, Any]) -> Application:
    """Application builder for Serve config files: args `root` (required), `replicas`,
    `shards`, `shard_cpus`, `shard_memory_gb`, `max_retrievals` and `allowed_hosts` (a list of
    host names; see `build_app`)."""
    if "root" not in args or not str(args["root"]).strip():
        raise ValueError("the links application needs args.root: a dataset folder or s3://...")
    unknown = sorted(set(args) - set(APP_ARGS))
    if unknown:
        raise ValueError(f"unknown args for the links application: {unknown}")
    given = {name: _arg(args, name) for name in args if name not in ("root", "allowed_hosts")}
    if "allowed_hosts" in args:
        try:
            given["allowed_hosts"] = tuple(sorted(as_host_names(args["allowed_hosts"])))
        except ValueError as exc:
            raise ValueError(f"args.allowed_hosts: {exc}") from None
    check_root(str(args["root"]), given.get("shards"))
    return build_app(str(args["root"]), **given)


def direct_ingress_env(port: int) -> dict[str, str]:
    """The environment under which Ray Serve's HTTP ingress replica serves on `port` itself.

    Ray reads it when it starts (its controller and replicas inherit it). A released port is
    taken back at once, so a restarted replica answers on the same port; and a stopping
    replica drains for a second, not 30: there is no load balancer in front to leave.
    """
    return {
        "RAY_SERVE_ENABLE_DIRECT_INGRESS": "1",
        "RAY_SERVE_DIRECT_INGRESS_MIN_HTTP_PORT": str(port),
        "RAY_SERVE_DIRECT_INGRESS_MAX_HTTP_PORT": str(port + 1),  # exclusive
        "RAY_SERVE_PORT_QUARANTINE_S": "0",
        "RAY_SERVE_DIRECT_INGRESS_MIN_DRAINING_PERIOD_S": "1",
    }


def bindable_port(host: str, port: int) -> int:
    """`port` (a free one if 0) if it can be bound on `host`, else ValueError naming why."""
    try:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
            # As servers bind: connections that just closed do not hold the port.
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind((host, port))
            return probe.getsockname()[1]
    except OSError as exc:
        raise ValueError(f"cannot serve on {host} port {port}: {exc.strerror}") from None


#: Where the kernel's ephemeral ports begin when /proc does not say (Linux's default).
EPHEMERAL_LOW = 32768
#: How far below the ephemeral range a port for Serve is looked for.
QUIET_PORTS = 12_000


def ephemeral_low() -> int:
    """The first port the kernel hands out to a socket bound to port 0."""
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return EPHEMERAL_LOW


def quiet_port(host: str) -> int:
    """A port free on `host` now and below the kernel's ephemeral range, for a listener Serve
    binds later: Ray's processes bind ephemeral ports by the dozen as they start, between this
    choice and Serve's bind, and a port from that range could be taken meanwhile; the kernel
    never hands out one below it. A free ephemeral port if none below is free."""
    low = ephemeral_low()
    draw = random.Random()
    for _ in range(100):
        try:
            return bindable_port(host, draw.randrange(max(1024, low - QUIET_PORTS), low))
        except ValueError:
            continue
    return bindable_port(host, 0)


def check_fits(
    replicas: int,
    shards: int | None,
    shard_cpus: float,
    shard_memory_gb: float | None,
    resources: dict[str, float],
) -> None:
    """ValueError unless the app of `build_app` fits in a Ray of these total `resources`."""
    cpus = float(replicas)  # the gateway: one CPU a replica
    memory = 0.0
    if shards:
        cpus += shards * replicas * shard_cpus
        memory = shards * replicas * (shard_memory_gb or 0.0) * 1e9
    have_cpus = resources.get("CPU", 0.0)
    if cpus > have_cpus + 1e-9:
        each = "1 a gateway replica" + (f", {shard_cpus:g} a partition replica" if shards else "")
        raise ValueError(
            f"the app needs {cpus:g} CPUs ({each}) and this Ray has {have_cpus:g}: serve "
            "fewer replicas or partitions (--shards), or give partitions fewer CPUs (--shard-cpus)"
        )
    have_memory = resources.get("memory", 0.0)
    if memory > have_memory:
        raise ValueError(
            f"the partitions reserve {memory / 1e9:.1f} GB and this Ray has "
            f"{have_memory / 1e9:.1f} GB to give: lower --shard-memory-gb"
        )


def fit_partition_cpus(replicas: int, shards: int, resources: dict[str, float]) -> float:
    """CPUs each partition replica reserves on one machine's Ray of these `resources`:
    PARTITION_CPUS if the app fits so, else an equal share of what the gateway's replicas (one
    CPU each) leave, rounded down to Ray's steps (1 / CPU_STEPS); ValueError if they leave
    none."""
    have = resources.get("CPU", 0.0)
    if float(replicas) + shards * replicas * PARTITION_CPUS <= have + 1e-9:
        return PARTITION_CPUS
    left = math.floor(round((have - replicas) * CPU_STEPS, 6))  # in steps
    share = max(left, 0) // (shards * replicas)
    if share == 0:
        raise ValueError(
            f"this Ray has {have:g} CPUs and the gateway takes {replicas} (one a replica): "
            "none is left for the partitions; serve fewer replicas, or no --shards"
        )
    return share / CPU_STEPS


def run_server(
    root: str,
    host: str = "127.0.0.1",
    port: int = 8000,
    replicas: int = 1,
    blocking: bool = True,
    shards: int | None = None,
    shard_cpus: float | None = None,
    shard_memory_gb: float | None = None,
    allowed_hosts: tuple[str, ...] | list[str] = (),
) -> None:
    """Serve `root` on http://host:port/ (Ray local unless RAY_ADDRESS) until Ctrl-C; with
    `shards`, split the index into that many partitions, `IndexPartition` deployments
    (`build_app`), each replica reserving `shard_cpus` CPUs (default PARTITION_CPUS).

    When this call starts Ray, the request gate (`serve.http.gate`) answers on host:port and passes
    whole requests to Serve on loopback: to the replica itself when there is one (of the
    gateway, with partitions; `direct_ingress_env`), else to Serve's proxy. On a Ray that was
    running already, Serve's proxy answers on host:port itself. On a Ray it starts itself,
    partitions given no `shard_cpus` share what the gateway leaves when PARTITION_CPUS each
    would not fit (`fit_partition_cpus`, said in one line on stderr), and an app that cannot
    fit is refused at once (ValueError naming what it needs), where Serve would wait for
    resources forever.
    """
    import ray

    from links_ray.cluster.connect import connect, is_loopback

    check_root(root, shards)  # a wrong ROOT is one line here, not a replica failing to start
    cpus = PARTITION_CPUS if shard_cpus is None else shard_cpus
    hosts = {"allowed_hosts": allowed_hosts}
    app = build_app(root, replicas, shards, cpus, shard_memory_gb, **hosts)  # checks them first
    local = not ray.is_initialized() and not os.environ.get("RAY_ADDRESS")
    direct = replicas == 1 and local
    serve_host, proxy_port, gate = host, port, None
    if local:
        # Serve answers only the gate, on loopback; the gate answers the user on host:port.
        bindable_port(host, port)  # else the command would fail after Ray's start
        serve_host, proxy_port = LOOPBACK, quiet_port(LOOPBACK)
        upstream_port = proxy_port
        if direct:
            upstream_port = quiet_port(LOOPBACK)
            os.environ.update(direct_ingress_env(upstream_port))
        gate = GateThread(RequestGate(host, port, upstream_port, as_host_names(allowed_hosts)))
    if blocking:
        # A service manager stops with SIGTERM: shut down as on Ctrl-C, not with a stack
        # trace, from the start on (set again once Ray has started: it sets its own).
        signal.signal(signal.SIGTERM, signal.default_int_handler)
    stop = True
    try:
        connect(loopback=is_loopback(host))  # Ray's own listeners stay on loopback too
        if blocking:
            signal.signal(signal.SIGTERM, signal.default_int_handler)
        if local:
            resources = ray.cluster_resources()
            if shards and shard_cpus is None:
                cpus = fit_partition_cpus(replicas, shards, resources)
                if cpus < PARTITION_CPUS:
                    print(
                        f"links-ray: this Ray has {resources.get('CPU', 0.0):g} CPUs and the "
                        f"gateway takes {replicas}: each of the {shards * replicas} partition "
                        f"replicas reserves {cpus:g} CPU (--shard-cpus to choose)",
                        file=sys.stderr,
                        flush=True,
                    )
                    app = build_app(root, replicas, shards, cpus, shard_memory_gb, **hosts)
            check_fits(replicas, shards, cpus, shard_memory_gb, resources)
        # Serve's controller, proxy and replicas report each step of a start-up at INFO; the
        # command prints its own line when it serves, and Serve's warnings still show.
        quiet = {"enable_access_log": False, "log_level": "WARNING"}
        logging.getLogger("ray.serve").setLevel(logging.WARNING)
        serve.start(http_options={"host": serve_host, "port": proxy_port}, logging_config=quiet)
        serve.run(app, name="links", route_prefix="/", logging_config=quiet)
        if gate is not None:
            gate.start()
            _running_gates.append(gate)
        shown = f"[{host}]" if ":" in host else host
        print(f"links-ray: serving {root} at http://{shown}:{port}/ (API under /api)", flush=True)
        if not blocking:
            stop = False
            return
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        print("links-ray: shutting down", flush=True)
    finally:
        if stop:
            stop_serving(ray_started=local)
            if blocking:
                # The process ends next: frozen, the heap of the libraries it loaded is left
                # out of the interpreter's last collections, which would walk all of it.
                gc.freeze()


#: The request gates `run_server` started in this process, which `stop_serving` stops.
_running_gates: list[GateThread] = []


def stop_serving(ray_started: bool) -> None:
    """Stop Serve, then Ray if this process started it, in bounded time: the request gates
    this process runs stop listening and let the requests they passed on finish, for at most
    SHUTDOWN_DRAIN_S; the replicas drain what is left for as long (a replica with none stops
    at once),
    Serve's controller gets SHUTDOWN_STOP_S more to stop them and the proxies, then Ray stops.
    `serve.shutdown()` alone takes no bound (it waits for the controller, then each replica,
    by Serve's own timeouts) and leaves Ray to the interpreter's exit."""
    import ray

    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second one must not cut the drain short
    while _running_gates:  # no new requests; those under way finish first
        _running_gates.pop().stop(drain_s=SHUTDOWN_DRAIN_S)
    # `serve.shutdown()` with a bound: it takes none; its client's `shutdown` does.
    client = serve.context._get_global_client(raise_if_no_controller_running=False)
    if client is not None:
        client.shutdown(timeout_s=SHUTDOWN_DRAIN_S + SHUTDOWN_STOP_S)
    serve.context._disconnect()
    if ray_started:
        ray.shutdown()
