"""`links bench retrieve`: index build, load and memory, latency in process and over HTTP, and
recall@3 against exact brute force, on the cached benchmark dataset (`bench.data`); or, with
`--root`, on a seeded draw of a root's curated paths (`data.path_draw`), in process only."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.request

import numpy as np

from links_ray.bench.data import folder_bytes, retrieval_dataset
from links_ray.bench.held_out import held_out_queries
from links_ray.bench.machine import machine_info
from links_ray.data.path_draw import PathDraw
from links_ray.engine.kinematics.paths import normalize_path

#: Measures the memory an index takes once loaded, in a fresh process: resident set growth.
_RESIDENT_PROBE = """
import json, sys
def rss():
    return int(open("/proc/self/status").read().split("VmRSS:")[1].split()[0]) * 1024
from links_ray.data.path_draw import PathDraw
from links_ray.search.index import RetrievalIndex
before = rss()
draw = None if sys.argv[2] == "all" else PathDraw(int(sys.argv[2]), int(sys.argv[3]))
index = RetrievalIndex.open(sys.argv[1], draw=draw)
index.warm(seconds=1.0)
print(json.dumps({"resident": rss() - before, "held": index.nbytes, "paths": len(index)}))
"""


def _resident_bytes(root: str, draw: PathDraw | None) -> dict:
    """`_RESIDENT_PROBE`'s record for the index of `root` (of the draw, when given)."""
    drawn = ["all", "0"] if draw is None else [str(draw.paths), str(draw.seed)]
    done = subprocess.run(
        [sys.executable, "-c", _RESIDENT_PROBE, root, *drawn],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def bench_retrieve(
    paths: int = 1_000_000,
    queries: int = 1000,
    recall_queries: int = 100,
    rebuild: bool = True,
    root: str | None = None,
    seed: int = 0,
) -> dict:
    """Index build, load and memory; latency in process and over HTTP; recall@3 against
    exact brute force.

    With `root`, the index is of the seeded draw of `paths` of its curated paths
    (`PathDraw(paths, seed)`) and latency is measured in process only: `links serve` opens a
    root's whole index.

    Queries are paths of mechanisms drawn afresh (held out of the dataset), neither arcs nor
    circles, given in a random frame: moved, turned, scaled and sometimes mirrored. Latency
    is timed on `queries` of them after the index's warm-up (`RetrievalIndex.warm`, which the
    Serve replica also runs before it takes traffic); recall on the first `recall_queries`.
    Without `rebuild`, a saved index is loaded and its recorded build time reported.
    """
    from links_ray.data.store import Store
    from links_ray.search.cache import cache_folder
    from links_ray.search.index import RetrievalIndex

    start = time.perf_counter()
    draw = None if root is None else PathDraw(paths, seed)
    root = retrieval_dataset(paths) if root is None else root
    dataset_s = time.perf_counter() - start
    disk = {
        table: folder_bytes(os.path.join(root, table))
        for table in (sorted(os.listdir(root)) if os.path.isdir(root) else [])
        if not table.startswith("_")
    }
    start = time.perf_counter()
    index = RetrievalIndex.open(root, rebuild=rebuild, draw=draw)
    build_s = time.perf_counter() - start
    if not index.build_s:  # loaded: the saved index's own build time
        saved = Store.open(root).read_json(f"{cache_folder(0, 1, draw)}/current.json") or {}
        build_s = float(saved.get("build_s", float("nan")))
    del index
    start = time.perf_counter()
    index = RetrievalIndex.open(root, draw=draw)
    load_s = time.perf_counter() - start
    resident = _resident_bytes(root, draw)
    held_out = held_out_queries(max(queries, recall_queries), seed=99)
    index.warm()
    in_process = []
    for query in held_out[:queries]:
        start = time.perf_counter()
        index.retrieve(query)
        in_process.append(time.perf_counter() - start)

    truth, brute_force_s = exact_truth(index, held_out[:recall_queries])
    hits = 0
    for query, exact in zip(held_out[:recall_queries], truth, strict=True):
        found = {row for row, _, _ in index.ranked(normalize_path(query))}
        hits += len(found & {row for row, _, _ in exact})
    probing = _probing(index, held_out[:recall_queries], truth)
    over_http = [] if draw is not None else _over_http(root, held_out, queries)
    large = len(index) >= 5_000_000
    return {
        "benchmark": "retrieve",
        "machine": machine_info(),
        "paths": len(index),
        "draw": None if draw is None else {"paths": draw.paths, "seed": draw.seed},
        "dataset_s": dataset_s,
        "disk_bytes": disk,
        "build_s": build_s,
        "load_s": load_s,
        "index_bytes": index.nbytes,
        "resident_bytes": resident["resident"],
        **_percentiles("", over_http),
        **_percentiles("in_process_", in_process),
        "recall_at_3": hits / (3 * recall_queries),
        "recall_queries": recall_queries,
        "brute_force_s": brute_force_s,
        "probing": probing,
        "queries": queries,
        "targets": {
            "p50_ms": 100 if large else 50,
            "p99_ms": 300 if large else 200,
            "recall_at_3": 0.95,
            "resident_bytes_per_path": 600,
        },
    }


def _percentiles(prefix: str, seconds: list[float]) -> dict:
    """p50, p99 and the slowest of these times in ms, keyed with `prefix` (None without any)."""
    if not seconds:
        return {f"{prefix}p50_ms": None, f"{prefix}p99_ms": None, f"{prefix}max_ms": None}
    return {
        f"{prefix}p50_ms": float(np.percentile(seconds, 50) * 1e3),
        f"{prefix}p99_ms": float(np.percentile(seconds, 99) * 1e3),
        f"{prefix}max_ms": float(np.max(seconds) * 1e3),
    }


def _over_http(root: str, held_out: list[np.ndarray], queries: int) -> list[float]:
    """Seconds each of `queries` retrievals took over HTTP, `root` served as `links serve`
    serves it (after one untimed request)."""
    # Served as `links serve` serves: Ray started for it, the replica answering HTTP itself.
    import ray
    from ray import serve

    from links_ray.serve.app import bindable_port, run_server

    ray.shutdown()  # generating the dataset may have started one
    port = bindable_port("127.0.0.1", 0)
    run_server(root, port=port, blocking=False)
    over_http = []
    try:
        for query in [held_out[0], *held_out[:queries]]:
            body = json.dumps({"points": query.tolist(), "k": 3}).encode()
            request = urllib.request.Request(
                f"http://127.0.0.1:{port}/api/retrieve",
                data=body,
                headers={"Content-Type": "application/json"},
            )
            start = time.perf_counter()
            with urllib.request.urlopen(request, timeout=60) as response:
                response.read()
            over_http.append(time.perf_counter() - start)
    finally:
        serve.shutdown()
    return over_http[1:]


def exact_truth(index: object, queries: list[np.ndarray]) -> tuple[list[list], float]:
    """The exact k = 3 best (row, chamfer, variant) of each query by brute force (all queries
    in one pass over the stored points), and the seconds the pass took.

    The answer is saved beside the data, keyed by the indexed shards' fingerprint and the
    queries' bytes, and read back on a later run over the same data and queries, since the
    pass grows with the dataset and is long on a large one. Rows are kept as path ids, which
    do not depend on the index's row order.
    """
    import hashlib

    from links_ray.data.store import Store

    key = hashlib.sha256(index.fingerprint.encode())
    for query in queries:
        key.update(np.ascontiguousarray(query, dtype=np.float64).tobytes())
    relative = f"_links/bench/truth-{key.hexdigest()[:16]}.json"
    saved = index.store.read_json(relative)
    if saved is None:
        start = time.perf_counter()
        truth = index.brute_force_many(queries)
        saved = {
            "brute_force_s": time.perf_counter() - start,
            "answers": [
                [
                    [int(index.path_ids(np.array([row]))[0]), distance, variant]
                    for row, distance, variant in exact
                ]
                for exact in truth
            ],
        }
        try:
            Store.open(index.store.uri).write_json(relative, saved)
        except OSError:  # a read-only root: measure again next time
            pass
    path_ids = index.path_id
    order = np.argsort(path_ids)
    truth = []
    for answer in saved["answers"]:
        wanted = np.array([path_id for path_id, _, _ in answer], dtype=np.int64)
        rows = order[np.searchsorted(path_ids, wanted, sorter=order)]
        truth.append([(int(row), a[1], a[2]) for row, a in zip(rows, answer, strict=True)])
    return truth, float(saved["brute_force_s"])


def _probing(index: object, queries: list[np.ndarray], truth: list[list]) -> list[dict]:
    """Recall@3 and the in-process search time (`ranked`) at a few scan sizes: how the
    coarse lists trade recall for time. One entry, every row, for an index of one list."""
    from links_ray.search.query import PROBED_ROWS

    sizes = (PROBED_ROWS // 4, PROBED_ROWS // 2, PROBED_ROWS, 2 * PROBED_ROWS)
    sizes = [size for size in sizes if size < len(index)] + [len(index)]
    normalized = [normalize_path(query) for query in queries]
    found = []
    for size in sizes:
        hits, times = 0, []
        for query, exact in zip(normalized, truth, strict=True):
            start = time.perf_counter()
            ranked = index.ranked(query, probed=size)
            times.append(time.perf_counter() - start)
            hits += len({row for row, _, _ in ranked} & {row for row, _, _ in exact})
        found.append(
            {
                "probed_rows": size,
                "recall_at_3": hits / (3 * len(queries)),
                "p50_ms": float(np.percentile(times, 50) * 1e3),
            }
        )
    return found


def format_retrieve(result: dict) -> str:
    """Retrieval latency, recall and memory beside the targets."""
    targets, paths = result["targets"], result["paths"]
    disk = ", ".join(f"{t} {b / 1e9:.1f} GB" for t, b in result["disk_bytes"].items())
    draw = result.get("draw")
    drawn = "" if draw is None else f", the draw of seed {draw['seed']}"
    over_http = (
        "over HTTP: not measured (`links serve` serves a root's whole index, not a draw)"
        if result["p50_ms"] is None
        else f"over HTTP: p50 {result['p50_ms']:.1f} ms, p99 {result['p99_ms']:.1f} ms, "
        f"slowest {result['max_ms']:.0f} ms of {result['queries']} "
        f"(targets {targets['p50_ms']} / {targets['p99_ms']} ms)"
    )
    return "\n".join(
        [
            f"{paths:,} curated paths{drawn} ({disk}); index built in {result['build_s']:.0f} s, "
            f"loaded in {result['load_s']:.1f} s",
            f"memory: {result['resident_bytes'] / paths:.0f} bytes resident per path "
            f"(target {targets['resident_bytes_per_path']}), "
            f"{result['index_bytes'] / paths:.0f} held by the index arrays",
            over_http,
            f"in process: p50 {result['in_process_p50_ms']:.1f} ms, "
            f"p99 {result['in_process_p99_ms']:.1f} ms, "
            f"slowest {result['in_process_max_ms']:.0f} ms",
            f"recall@3 against exact brute force: {result['recall_at_3']:.3f} on "
            f"{result['recall_queries']} held-out queries (target {targets['recall_at_3']}; "
            f"brute force took {result['brute_force_s']:.0f} s)",
            "rows scanned per query: "
            + "; ".join(
                f"{p['probed_rows']:,} recall {p['recall_at_3']:.3f} p50 {p['p50_ms']:.0f} ms"
                for p in result["probing"]
            ),
        ]
    )
