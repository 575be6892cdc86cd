"""`links bench serve`: the app under load. Clients retrieve while another checks health and
simulates, with one index in the front and with the index split into shards."""

from __future__ import annotations

import json
import os
import urllib.request

import numpy as np

from links_ray.cli import report
from links_ray.cli.bench import machine_info
from links_ray.cli.bench_data import retrieval_dataset
from links_ray.search.held_out import held_out_queries
from links_ray.serve.load_clients import finish_load, probe_loop, retrieval_load, wait_for_port


def _ms(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q) * 1e3) if values else None


def bench_serve(
    shards: list[int] | None = None,
    seconds: float = 30.0,
    clients: int = 32,
    paths: int = 60_000,
    root: str | None = None,
) -> dict:
    """Serving under load: `clients` clients retrieving for `seconds` while another checks
    health and simulates, for each count in `shards` (0: one index in the front). The app is
    served as `links serve` serves it, on a Ray started for the benchmark (one for all the
    runs), the front answering HTTP itself.

    Reports retrievals answered per second, p50/p99 of the answered retrievals and of the
    health checks and simulations, and the 503s. Shard replicas get an equal share of the
    CPUs the front leaves (at most one each). The clients run on the same machine as the
    server.
    """
    import ray
    from ray import serve

    from links_ray.cluster.connect import connect
    from links_ray.search.index import RetrievalIndex
    from links_ray.serve.app import (
        bindable_port,
        build_app,
        check_root,
        direct_ingress_env,
        fit_shard_cpus,
    )

    counts = [0, 1, 2] if shards is None else shards
    root = root or retrieval_dataset(paths)
    for count in counts:
        check_root(root, count or None)
    queries = held_out_queries(64, seed=77)
    ray.shutdown()  # generating the dataset may have started one
    port = _listening_port()
    os.environ.update(direct_ingress_env(port))
    connect()
    no_access_log = {"enable_access_log": False}
    runs = []
    try:
        for count in counts:
            parts = max(count, 1)
            for part in range(parts):  # built before the run, not during it
                RetrievalIndex.open(root, part=part, parts=parts)
            shard_cpus = fit_shard_cpus(1, count, ray.cluster_resources()) if count else None
            app = build_app(root, shards=count or None, shard_cpus=shard_cpus or 1.0)
            wait_for_port(port)  # the last run's front may still be letting go of it
            serve.start(
                http_options={"host": "127.0.0.1", "port": bindable_port("127.0.0.1", 0)},
                logging_config=no_access_log,
            )
            try:
                serve.run(app, name="links", route_prefix="/", logging_config=no_access_log)
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/health") as response:
                    indexed = json.loads(response.read())["paths"]
                load = retrieval_load(port, queries, seconds, clients)
                probes = probe_loop(port, seconds)
                record = finish_load(load)
            finally:
                serve.shutdown()
            answered = record["statuses"].get("200", 0)
            runs.append(
                {
                    "shards": count,
                    "shard_cpus": shard_cpus,
                    "paths": indexed,
                    "seconds": record["seconds"],
                    "retrievals_per_s": answered / record["seconds"],
                    "retrieve_p50_ms": _ms(record["latencies"], 50),
                    "retrieve_p99_ms": _ms(record["latencies"], 99),
                    "health_p50_ms": _ms(probes["health"], 50),
                    "health_p99_ms": _ms(probes["health"], 99),
                    "simulate_p50_ms": _ms(probes["simulate"], 50),
                    "simulate_p99_ms": _ms(probes["simulate"], 99),
                    "retrieve_statuses": record["statuses"],
                    "probe_statuses": probes["statuses"],
                    "busy_503": record["statuses"].get("503", 0),
                    # The machine's own load meanwhile (other users share it).
                    "load_average_1min": os.getloadavg()[0],
                }
            )
    finally:
        ray.shutdown()
    return {
        "benchmark": "serve",
        "machine": machine_info(),
        "root": root,
        "clients": clients,
        "runs": runs,
    }


def _listening_port() -> int:
    """A free loopback port below Linux's ephemeral range (32768+), for the front to answer on
    run after run: in that range an outgoing connection (Ray opens many as an app starts) may
    take it between two runs."""
    from links_ray.serve.app import bindable_port

    rng = np.random.default_rng()
    for _ in range(200):
        try:
            return bindable_port("127.0.0.1", int(rng.integers(23_000, 30_000)))
        except ValueError:
            continue
    return bindable_port("127.0.0.1", 0)


def format_serve(result: dict) -> str:
    """Throughput and latencies under load, by shard count."""
    rows = []
    for run in result["runs"]:
        other = sum(
            n for status, n in run["retrieve_statuses"].items() if status not in ("200", "503")
        )
        other += sum(n for key, n in run["probe_statuses"].items() if not key.endswith(" 200"))

        def pair(name: str, run: dict = run) -> str:
            p50, p99 = run[f"{name}_p50_ms"], run[f"{name}_p99_ms"]
            return "-" if p50 is None else f"{p50:.1f} / {p99:.1f}"

        rows.append(
            [
                run["shards"] or "none",
                f"{run['retrievals_per_s']:.1f}",
                pair("retrieve"),
                pair("health"),
                pair("simulate"),
                run["busy_503"],
                other,
                f"{run['load_average_1min']:.1f}",
            ]
        )
    header = ["shards", "retrievals/s", "retrieve p50/p99 ms", "health p50/p99 ms"]
    header += ["simulate p50/p99 ms", "503s", "other", "load avg"]
    return "\n".join(
        [
            f"{result['clients']} clients retrieving, one checking health and simulating "
            f"({result['runs'][0]['paths']:,} curated paths)"
            if result["runs"]
            else "no runs",
            report.table(header, rows),
        ]
    )
