"""The `links` command line: parses arguments and calls library functions.

Errors a user can cause end as one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from links_ray import __version__
from links_ray.cli import bench, export, export_dataset, import_release, report
from links_ray.cli.bench_synthesis import BENCH_SECONDS
from links_ray.cli.demo import run_demo
from links_ray.cli.warm import format_warm, note_compiling, warm
from links_ray.engine.inputs import (
    DEFAULT_K,
    DEFAULT_SYNTHESIS_SECONDS,
    MAX_CURVE_FILE_BYTES,
    MAX_DATASET_JOINTS,
    MAX_K,
    MAX_SYNTHESIS_ITERATIONS,
    MAX_SYNTHESIS_SECONDS,
    MAX_TRANSMISSION_DEG,
    MIN_JOINTS,
    as_constraints,
    as_max_joints,
    as_timing,
    as_transmission_deg,
    validate_synthesis,
    validate_synthesis_work,
)
from links_ray.engine.topology import TOPOLOGY_RULES
from links_ray.interop.curve_files import DEFAULT_CURVE_POINTS


def _report(args: argparse.Namespace, result: dict, formatted: Callable[[dict], str]) -> None:
    """A command's result: one JSON object with --json, else the human-readable table; for
    the commands the contract has print JSON (`stats`, `retrieve`), JSON also when the output
    is not a terminal (a script reading it), unless --table."""
    table = getattr(args, "table", None)
    piped = table is not None and not table and not sys.stdout.isatty()
    report.emit(result, formatted, args.json or piped)


def _bench_simulate(args: argparse.Namespace) -> None:
    _report(args, bench.bench_simulate(repeats=args.repeats), bench.format_simulate)


def _bench_simulate_one(args: argparse.Namespace) -> None:
    result = bench.bench_simulate_one(mechanisms=args.mechanisms)
    _report(args, result, bench.format_simulate_one)


def _bench_sample(args: argparse.Namespace) -> None:
    _report(args, bench.bench_sample(per_joint_count=args.topologies), bench.format_sample)


def _tables(args: argparse.Namespace) -> dict:
    """`--tables` as the library takes it; absent, the library's default (the paper's set)."""
    return {} if args.tables is None else {"tables": args.tables}


def _generate(args: argparse.Namespace) -> None:
    from links_ray.cluster.generation import generate  # imports Ray: only when asked for

    summary = generate(
        args.out,
        args.mechanisms,
        seed=args.seed,
        workers=args.workers,
        sampler=args.sampler,
        address=args.address,
        topologies_per_shard=args.shard_topologies,
        topology_rules=args.topology_rules,
        min_transmission_deg=args.min_transmission,
        starting=lambda: note_compiling("generate"),
        **_tables(args),
    )
    if summary.get("nothing_to_do"):
        print(
            f"links generate: nothing to do: {args.out} holds all {args.mechanisms:,} "
            "mechanisms of this plan",
            file=sys.stderr,
        )
    _report(args, summary, report.format_generate)


def _run_bench(
    args: argparse.Namespace, run: Callable[[], dict], formatted: Callable[[dict], str]
) -> None:
    """Run a benchmark that starts Ray, its messages kept off stdout (the result's), and report
    the result."""
    with contextlib.redirect_stdout(sys.stderr):
        result = run()
    _report(args, result, formatted)


def _bench_generate(args: argparse.Namespace) -> None:
    from links_ray.cli import bench_generate  # imports Ray: only when asked for

    _run_bench(
        args,
        lambda: bench_generate.bench_generate(mechanisms=args.mechanisms),
        bench_generate.format_generate,
    )


def _curate(args: argparse.Namespace) -> None:
    from links_ray.cluster.curation import curate  # imports Ray: only when asked for

    summary = curate(
        args.root,
        seed=args.seed,
        workers=args.workers,
        address=args.address,
        starting=lambda: note_compiling("curate"),
        **_tables(args),
    )
    _report(args, summary, report.format_curate)


def _index(args: argparse.Namespace) -> None:
    from links_ray.data.store import Store
    from links_ray.search.cache import INDEX_FOLDER, cache_folder
    from links_ray.search.index import RetrievalIndex
    from links_ray.serve.app import check_root  # imports Ray Serve: only when asked for

    parts = args.shards or 1
    check_root(args.root, args.shards)  # what `links serve --shards` would refuse, at once
    # Opened for writing: a root whose keys cannot save the index fails here, not after the
    # builds (`RetrievalIndex.open` on a read-only root builds in memory and saves nothing).
    # Its requests are tried as often as curation's, to ride out a store's brief refusals
    # over a long build.
    store = Store.open(args.root, attempts=10)
    start = time.perf_counter()
    made = []
    for part in range(parts):
        began = time.perf_counter()
        index = RetrievalIndex.open(store, rebuild=args.rebuild, part=part, parts=parts)
        saved = store.read_json(f"{cache_folder(part, parts)}/current.json") or {}
        if saved.get("fingerprint") != index.fingerprint or saved.get("rows") != len(index):
            raise OSError(
                f"{store.uri}: part {part} of {parts} of the index was built but not saved "
                f"under {store.uri}/{cache_folder(part, parts)}/"
            )
        made.append(
            {
                "part": part,
                "paths": len(index),
                "built": index.build_s > 0,
                "seconds": round(time.perf_counter() - began, 3),
            }
        )
        del index  # one part's arrays in memory at a time
    summary = {
        "root": store.uri,
        "paths": sum(entry["paths"] for entry in made),
        "parts": parts,
        "built": sum(entry["built"] for entry in made),
        "seconds": round(time.perf_counter() - start, 3),
        "folder": f"{store.uri}/{INDEX_FOLDER}",
        "by_part": made,
    }
    _report(args, summary, report.format_index)


def _stats(args: argparse.Namespace) -> None:
    from links_ray.data.stats import dataset_stats

    stats = dataset_stats(args.root, sample_topologies=args.sample_topologies)
    if args.plots:
        from links_ray.cli.figures import write_figures

        stats["plots"] = write_figures(args.root, args.plots, stats)
    _report(args, stats, report.format_stats)


def _serve(args: argparse.Namespace) -> None:
    from links_ray.serve.app import run_server  # imports Ray Serve: only when asked for

    note_compiling("serve")
    run_server(
        args.root,
        host=args.host,
        port=args.port,
        replicas=args.replicas,
        shards=args.shards,
        shard_cpus=args.shard_cpus,
        shard_memory_gb=args.shard_memory_gb,
        allowed_hosts=args.allow_host,
    )


def _retrieve(args: argparse.Namespace) -> None:
    from links_ray.search.index import RetrievalIndex

    points, _ = _query_points(args)
    as_max_joints(args.max_joints)  # before the index loads
    note_compiling("retrieve")
    index = RetrievalIndex.open(args.root)
    start = time.perf_counter()
    results = index.retrieve(
        points, k=args.k, min_transmission=args.min_transmission, max_joints=args.max_joints
    )
    took_ms = (time.perf_counter() - start) * 1e3
    _report(args, {"results": results, "took_ms": took_ms}, report.format_retrieve)


def _synthesize(args: argparse.Namespace) -> None:
    from links_ray.engine.synthesis import synthesize
    from links_ray.search.index import RetrievalIndex

    points, closed = _query_points(args)
    partial = args.partial or not closed
    # Before the index loads:
    validate_synthesis_work(args.seconds, args.seed, args.iterations)
    validate_synthesis(points, args.k, args.seconds, partial)
    as_transmission_deg(args.min_transmission, "min_transmission")
    as_max_joints(args.max_joints)
    constraints = as_constraints(_json_file(args.constraints, "--constraints"))
    timing = args.timing if args.timing in (None, True) else _json_file(args.timing, "--timing")
    as_timing(timing, len(points), partial)
    note_compiling("synthesize")
    index = RetrievalIndex.open(args.root)
    start = time.perf_counter()
    results = synthesize(
        index,
        points,
        k=args.k,
        seconds=args.seconds,
        partial=partial,
        min_transmission=args.min_transmission,
        max_joints=args.max_joints,
        front=args.front,
        constraints=constraints,
        timing=timing,
        seed=args.seed,
        iterations=args.iterations,
    )
    took_ms = (time.perf_counter() - start) * 1e3
    answer = {"results": list(results), "took_ms": took_ms}
    if results.unmet is not None:
        answer["unmet"] = results.unmet
    _report(args, answer, report.format_synthesize)


def _json_file(path: str | None, option: str) -> object:
    """The JSON value in the file an option names (None without one); ValueError naming the
    option and the file if it cannot be read."""
    if path is None:
        return None
    try:
        with open(path, "rb") as stream:
            data = stream.read(MAX_CURVE_FILE_BYTES + 1)
        if len(data) > MAX_CURVE_FILE_BYTES:
            raise ValueError(f"{option} {path}: larger than {MAX_CURVE_FILE_BYTES:,} bytes")
        return json.loads(data)
    except OSError as exc:
        raise ValueError(f"{option} {path}: {exc.strerror or exc}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{option} {path}: not JSON ({exc})") from None


def _bench_synthesize(args: argparse.Namespace) -> None:
    from links_ray.cli import bench_synthesis

    if args.design:
        from links_ray.cli import bench_design

        if args.set or args.curve or args.iterations is not None or args.figure:
            raise ValueError(
                "--design runs the 8 targets at a time budget: no --set, --curve, "
                "--iterations or --figure"
            )
        _run_bench(
            args,
            lambda: bench_design.bench_design(
                seconds=args.seconds, paths=args.paths, seed=args.seed
            ),
            bench_design.format_design,
        )
        return
    _run_bench(
        args,
        lambda: bench_synthesis.bench_synthesize(
            seconds=args.seconds,
            paths=args.paths,
            seed=args.seed,
            figure=args.figure,
            iterations=args.iterations,
            use_set=args.set,
            only=tuple(args.curve or ()),
        ),
        bench_synthesis.format_synthesize,
    )


def _bench_import_release(args: argparse.Namespace) -> None:
    from links_ray.cli import bench_release

    _run_bench(
        args,
        lambda: bench_release.bench_import(batches=args.batches),
        bench_release.format_import,
    )


def _bench_retrieve(args: argparse.Namespace) -> None:
    from links_ray.cli import bench_retrieve

    _run_bench(
        args,
        lambda: bench_retrieve.bench_retrieve(paths=args.paths, rebuild=not args.reuse_index),
        bench_retrieve.format_retrieve,
    )


def _bench_serve(args: argparse.Namespace) -> None:
    from links_ray.cli import bench_serve

    _run_bench(
        args,
        lambda: bench_serve.bench_serve(
            shards=args.shards,
            seconds=args.seconds,
            clients=args.clients,
            paths=args.paths,
            root=args.root,
            largest_bodies=not args.no_largest_bodies,
        ),
        bench_serve.format_serve,
    )


def _bench_hostile(args: argparse.Namespace) -> None:
    from links_ray.cli import bench_hostile

    _run_bench(
        args,
        lambda: bench_hostile.bench_hostile(paths=args.paths, root=args.root),
        bench_hostile.format_hostile,
    )


def _demo(args: argparse.Namespace) -> None:
    note_compiling("demo")
    summary = run_demo(args.out, mechanisms=args.mechanisms, seed=args.seed, sampler=args.sampler)
    _report(args, summary, report.format_demo)


def _json_option(
    command: argparse.ArgumentParser, what: str = "the whole result", piped: bool = False
) -> None:
    """`--json`: print `what` as one JSON object instead of the short human summary. With
    `piped`, JSON is also the default when the output is not a terminal, and `--table`
    asks for the summary anyway."""
    command.add_argument("--json", action="store_true", help=f"print {what} as one JSON object")
    if piped:
        command.add_argument(
            "--table",
            action="store_true",
            help="print the short summary even when the output is not a terminal "
            "(default: JSON then, as scripts read it)",
        )


def _warm(args: argparse.Namespace) -> None:
    _report(args, warm(args.folder), format_warm)


def _query_points(args: argparse.Namespace) -> tuple[object, bool]:
    """The query's points and whether they close: `--points` as they are (closed), or the
    curve of `--curve` sampled evenly."""
    from links_ray.interop.curve_files import read_curve, read_points

    if args.points is not None:
        return read_points(args.points), True
    curve = read_curve(args.curve)
    return curve.points, curve.closed


def _max_joints_option(command: argparse.ArgumentParser) -> None:
    """`--max-joints J`, as retrieve and synthesize take it."""
    command.add_argument(
        "--max-joints",
        type=int,
        default=None,
        metavar="J",
        help="only mechanisms whose reduced mechanism (the joints the path needs) has at most "
        f"J joints ({MIN_JOINTS}-{MAX_DATASET_JOINTS}, default: any)",
    )


def _query_arguments(command: argparse.ArgumentParser, curve_help: str = "") -> None:
    """The dataset root, the drawn points' file or a drawing's curve, and k, as retrieve and
    synthesize take them."""
    command.add_argument("root", help="dataset root: a folder or s3://...")
    source = command.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--points", metavar="FILE", help='JSON file: [[x, y], ...] or {"points": [...]}'
    )
    source.add_argument(
        "--curve",
        metavar="FILE[#ID]",
        help="a curve in a drawing: .svg (a path or shape, #ID its id, else the first; y up), "
        ".dxf (an LWPOLYLINE, POLYLINE or SPLINE, #ID its layer, else the first), .csv (x,y "
        f"lines) or .json, sampled evenly to {DEFAULT_CURVE_POINTS} points{curve_help}",
    )
    command.add_argument(
        "-k",
        type=_positive_int,
        default=DEFAULT_K,
        help=f"results (1-{MAX_K}, default {DEFAULT_K})",
    )
    command.add_argument(
        "--min-transmission",
        type=float,
        default=0.0,
        metavar="DEG",
        help="only mechanisms whose least transmission angle is at least DEG degrees "
        f"(0-{MAX_TRANSMISSION_DEG:g}, default 0: all)",
    )


def _int_at_least(minimum: int, name: str) -> Callable[[str], int]:
    """An argparse type: an integer >= `minimum`, refused in words otherwise."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be a {name} integer, got {text}")
        return value

    return parse


_positive_int = _int_at_least(1, "positive")
_non_negative_int = _int_at_least(0, "non-negative")


def _port(text: str) -> int:
    """An argparse type: a TCP port, 1 to 65535."""
    port = _positive_int(text)
    if port > 65535:
        raise argparse.ArgumentTypeError(f"must be a port from 1 to 65535, got {text}")
    return port


def _positive_float(text: str) -> float:
    """An argparse type: a positive finite number, refused in words otherwise."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


class _Parser(argparse.ArgumentParser):
    """Usage mistakes end as one line (the usage is one `--help` away), exit status 2; every
    option's help says its default."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")

    def add_argument(self, *args: Any, **kwargs: Any) -> argparse.Action:
        action = super().add_argument(*args, **kwargs)
        default = action.default
        # By identity: a default of 0 is worth showing, unlike a flag's False.
        shown = not any(default is nothing for nothing in (None, False, argparse.SUPPRESS))
        if action.option_strings and shown and "default" not in (action.help or ""):
            if isinstance(default, list | tuple):
                default = ",".join(map(str, default))
            action.help = (
                f"{action.help} (default {default})" if action.help else f"default {default}"
            )
        return action


def _add_bench(
    benches: argparse._SubParsersAction,
    name: str,
    summary: str,
    run: Callable[[argparse.Namespace], None],
    size: tuple[str, int, str],
) -> argparse.ArgumentParser:
    """`links bench NAME [--json] [SIZE N]`: every benchmark has one size option."""
    bench_parser = benches.add_parser(name, help=summary)
    _json_option(bench_parser)
    option, default, meaning = size
    bench_parser.add_argument(
        option, type=_positive_int, default=default, help=f"{meaning} (default {default:,})"
    )
    bench_parser.set_defaults(run=run)
    return bench_parser


def build_parser() -> argparse.ArgumentParser:
    """The `links` command line: every command, its options and the function that runs it
    (`args.run`). The site's CLI reference is written from it."""
    parser = _Parser(prog="links", description="LINKS: planar linkage mechanisms and their paths.")
    parser.add_argument("--version", action="version", version=f"links-ray {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    demo = commands.add_parser(
        "demo", help="generate a few valid mechanisms with the engine and save them as JSON lines"
    )
    demo.add_argument("--out", default="links-demo", help="output folder (default links-demo)")
    demo.add_argument("--mechanisms", type=_positive_int, default=100)
    demo.add_argument("--seed", type=_non_negative_int, default=0)
    demo.add_argument("--sampler", choices=["sequential", "rejection"], default="sequential")
    _json_option(demo, "the summary")
    demo.set_defaults(run=_demo)

    warm_command = commands.add_parser(
        "warm",
        help="compile every kernel into numba's cache now (the container image does this)",
    )
    warm_command.add_argument(
        "--folder", default=None, help="work folder (default: a temporary one, removed after)"
    )
    _json_option(warm_command, "each stage's seconds")
    warm_command.set_defaults(run=_warm)

    generate = commands.add_parser(
        "generate", help="generate valid mechanisms on Ray into a folder or s3://bucket/prefix"
    )
    generate.add_argument("--out", required=True, help="dataset root: a folder or s3://...")
    generate.add_argument("--mechanisms", type=_positive_int, required=True)
    generate.add_argument("--seed", type=_non_negative_int, default=0)
    generate.add_argument(
        "--workers",
        type=_positive_int,
        default=None,
        help="generator actors (default: one per CPU)",
    )
    generate.add_argument("--sampler", choices=["sequential", "rejection"], default="sequential")
    generate.add_argument(
        "--address", default=None, help="Ray cluster address (default: RAY_ADDRESS or a local one)"
    )
    generate.add_argument(
        "--shard-topologies",
        type=_positive_int,
        default=None,
        help="topologies per shard (default 1000); rows do not depend on it, but a resumed "
        "run must use the same value",
    )
    generate.add_argument(
        "--tables",
        default=None,
        metavar="TABLES",
        help="tables to write, comma-separated: mechanisms and any of simulations, negatives "
        "(default all three); a resumed run must use the same",
    )
    generate.add_argument(
        "--topology-rules",
        choices=TOPOLOGY_RULES,
        default=TOPOLOGY_RULES[0],
        help="topology generator: links (the LINKS release's rules) or feasible (default "
        "%(default)s)",
    )
    generate.add_argument(
        "--min-transmission",
        type=float,
        default=0.0,
        metavar="DEG",
        help="keep only mechanisms whose least transmission angle is at least DEG degrees, "
        f"0 to {MAX_TRANSMISSION_DEG:g} (default 0: the paper's distribution)",
    )
    _json_option(generate, "the run's summary")
    generate.set_defaults(run=_generate)

    curate = commands.add_parser(
        "curate", help="Ray Data pass: normalized paths and the curated subset, with statistics"
    )
    curate.add_argument("root", help="dataset root: a folder or s3://...")
    curate.add_argument("--seed", type=_non_negative_int, default=0, help="curation draw seed")
    curate.add_argument("--workers", type=_positive_int, default=None)
    curate.add_argument("--address", default=None, help="Ray cluster address")
    curate.add_argument(
        "--tables",
        default=None,
        metavar="TABLES",
        help="tables to write, comma-separated: paths, curated or both (default both)",
    )
    _json_option(curate, "the pass's summary")
    curate.set_defaults(run=_curate)

    index_command = commands.add_parser(
        "index",
        help="build and save the retrieval index of a curated root (each part with --shards)",
    )
    index_command.add_argument("root", help="dataset root: a folder or s3://...")
    index_command.add_argument(
        "--shards",
        type=_positive_int,
        default=None,
        help="save the index split into N partitions, as `links serve --shards N` opens it "
        "(default: one index)",
    )
    index_command.add_argument(
        "--rebuild",
        action="store_true",
        help="build every part again, even one saved from the same curated shards",
    )
    _json_option(index_command, "the summary, with each part's paths and seconds")
    index_command.set_defaults(run=_index)

    stats = commands.add_parser("stats", help="dataset statistics, figures as PNG")
    stats.add_argument("root", help="dataset root: a folder or s3://...")
    stats.add_argument("--plots", default=None, help="folder for the PNG figures")
    stats.add_argument(
        "--sample-topologies",
        type=_positive_int,
        default=3,
        help="topologies per joint count when candidates per valid must be measured here",
    )
    _json_option(stats, "every statistic", piped=True)
    stats.set_defaults(run=_stats)

    serve = commands.add_parser("serve", help="Ray Serve app: the HTTP API and the studio at /")
    serve.add_argument("root", help="dataset root: a folder or s3://...")
    serve.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    serve.add_argument("--port", type=_port, default=8000, help="port (default 8000)")
    serve.add_argument(
        "--replicas",
        type=_positive_int,
        default=1,
        help="replicas of the app (with --shards: of the gateway and of each partition; default 1)",
    )
    serve.add_argument(
        "--shards",
        type=_positive_int,
        default=None,
        help="split the index into N partitions, each served by its own deployment, which "
        "the gateway asks at once (default: one index in the gateway)",
    )
    serve.add_argument(
        "--shard-cpus",
        type=_positive_float,
        default=None,
        help="CPUs Ray reserves for each partition replica (default 1, or on a Ray this "
        "command starts, if that does not fit, an equal share of what the gateway leaves)",
    )
    serve.add_argument(
        "--shard-memory-gb",
        type=_positive_float,
        default=None,
        help="memory Ray reserves for each partition replica, in GB (default none)",
    )
    serve.add_argument(
        "--allow-host",
        action="append",
        default=[],
        metavar="NAME",
        help="a host name the server answers to besides its addresses and localhost (the name "
        "a proxy or DNS gives it; repeatable; * for any): others get 400",
    )
    serve.set_defaults(run=_serve)

    retrieve = commands.add_parser(
        "retrieve", help="find mechanisms whose path matches the points in FILE (offline)"
    )
    _query_arguments(retrieve)
    _max_joints_option(retrieve)
    _json_option(retrieve, "the results (points and placed mechanisms included)", piped=True)
    retrieve.set_defaults(run=_retrieve)

    synthesize = commands.add_parser(
        "synthesize",
        help="find mechanisms for the curve in FILE and refine them onto it (offline)",
    )
    _query_arguments(synthesize, "; an open curve is matched as a stroke (as with --partial)")
    synthesize.add_argument(
        "--seconds",
        type=_positive_float,
        default=None,
        help=f"time budget, retrieval included (at most {MAX_SYNTHESIS_SECONDS:g}, "
        f"default {DEFAULT_SYNTHESIS_SECONDS:g})",
    )
    synthesize.add_argument(
        "--iterations",
        type=_positive_int,
        default=None,
        help=f"fixed work instead of a time budget: about this many refinement iterations "
        f"(at most {MAX_SYNTHESIS_ITERATIONS:,}); equal inputs give equal answers",
    )
    synthesize.add_argument(
        "--seed",
        type=_non_negative_int,
        default=0,
        help="seed of the random restarts (default 0)",
    )
    synthesize.add_argument(
        "--partial",
        action="store_true",
        help="the points are an open stroke: match them to part of a crank turn (the default "
        "for an open --curve)",
    )
    _max_joints_option(synthesize)
    synthesize.add_argument(
        "--front",
        action="store_true",
        help="answer the best mechanism of each joint count that beats every simpler one, "
        "simplest first, instead of the k best",
    )
    synthesize.add_argument(
        "--constraints",
        metavar="FILE",
        help='JSON file of design constraints in the drawing\'s units: {"pivots": [xmin, ymin, '
        'xmax, ymax], "footprint": [...], "max_link_ratio": R, "min_link": L, "max_link": L} '
        "(any of them); every result keeps them",
    )
    synthesize.add_argument(
        "--timing",
        nargs="?",
        const=True,
        default=None,
        metavar="FILE",
        help="prescribed timing: the points are reached at equal crank steps over a turn, in "
        "order, from a free start; or, with FILE, at the crank angles it lists (JSON, degrees, "
        "one per point)",
    )
    _json_option(synthesize, "the results (mechanisms included)")
    synthesize.set_defaults(run=_synthesize)

    export.add_command(commands)  # links export: cli/export.py
    export_dataset.add_command(commands, _positive_int)  # links export-dataset
    import_release.add_command(commands)  # links import-release

    bench_parser = commands.add_parser("bench", help="benchmarks")
    benches = bench_parser.add_subparsers(dest="bench", required=True)
    _add_bench(
        benches,
        "simulate",
        "the paper's Table 1: 10,000 random mechanisms, 200 steps",
        _bench_simulate,
        ("--repeats", 5, "timed runs of each method"),
    )
    _add_bench(
        benches,
        "simulate-one",
        "one mechanism a call: full turns a second of simulate, TopologySimulator, simulate_batch",
        _bench_simulate_one,
        ("--mechanisms", 200, "valid mechanisms (8-20 joints, five per topology)"),
    )
    _add_bench(
        benches,
        "sample",
        "position samplers: valid per core-second, candidates per valid",
        _bench_sample,
        ("--topologies", 10, "topologies per joint count"),
    )
    _add_bench(
        benches,
        "generate",
        "end-to-end generation on local Ray: valid mechanisms per core-second",
        _bench_generate,
        ("--mechanisms", 50_000, "mechanisms per run"),
    )
    retrieve_bench = _add_bench(
        benches,
        "retrieve",
        "retrieval latency and recall@3 on a cached curated dataset",
        _bench_retrieve,
        ("--paths", 1_000_000, "curated paths in the index"),
    )
    retrieve_bench.add_argument(
        "--reuse-index",
        action="store_true",
        help="load the saved index and report its recorded build time instead of rebuilding",
    )
    synthesize_bench = _add_bench(
        benches,
        "synthesize",
        "synthesis of the shipped target curves: retrieval-only and refined chamfer, seconds",
        _bench_synthesize,
        ("--paths", 1_000_000, "curated paths in the index"),
    )
    synthesize_bench.add_argument(
        "--seconds",
        type=_positive_float,
        default=None,
        help=f"budget per curve (default {BENCH_SECONDS:g}; with --set the synthesis default, "
        f"{DEFAULT_SYNTHESIS_SECONDS:g})",
    )
    synthesize_bench.add_argument(
        "--seed",
        type=_non_negative_int,
        default=0,
        help="seed of the curves' random frames (default 0, the benchmarks page's table)",
    )
    synthesize_bench.add_argument(
        "--iterations",
        type=_positive_int,
        default=None,
        help="fixed work per curve instead of --seconds (the seed seeds the restarts too)",
    )
    synthesize_bench.add_argument(
        "--figure",
        default=None,
        help="also draw every curve, its retrieved path and refined mechanism into this PNG",
    )
    synthesize_bench.add_argument(
        "--set",
        action="store_true",
        help="the curve set of links_ray.cli.curve_set (a tuning and a held-out half) instead "
        "of the 8 targets, reported per half and family; the figure shows the held-out half "
        "(needs the bench extra)",
    )
    synthesize_bench.add_argument(
        "--design",
        action="store_true",
        help="buildable answers instead: per target, the plain best, the front (simplest "
        "first), a pivot region and footprint kept, and the timed error, each at the budget "
        "(default the synthesis default)",
    )
    synthesize_bench.add_argument(
        "--curve",
        action="append",
        default=None,
        metavar="NAME",
        help="run only this curve (repeat for several); with --iterations its row is the same "
        "bit for bit as in a run of them all",
    )
    _add_bench(
        benches,
        "import-release",
        "the release's pickled files (exported from the bench set, batches of 100,000) "
        "imported: mechanisms per second, peak memory",
        _bench_import_release,
        ("--batches", 2, "release batches of 100,000 mechanisms"),
    )
    serve_bench = benches.add_parser(
        "serve",
        help="serving under load: retrievals per second, latencies, 503s, by shard count",
    )
    _json_option(serve_bench)
    serve_bench.add_argument(
        "--shards",
        type=_non_negative_int,
        action="append",
        default=None,
        help="partitions to serve with, 0 for one index in the gateway; repeat for several "
        "runs (default: 0, 1 and 2)",
    )
    serve_bench.add_argument(
        "--seconds", type=_positive_float, default=30.0, help="load per run (default 30)"
    )
    serve_bench.add_argument(
        "--clients", type=_positive_int, default=32, help="retrieving clients (default 32)"
    )
    serve_bench.add_argument(
        "--root",
        default=None,
        help="a curated dataset to serve (default: a cached one of --paths curated paths)",
    )
    serve_bench.add_argument(
        "--no-largest-bodies",
        action="store_true",
        help="skip the last run, of clients posting the largest simulations the limits allow",
    )
    serve_bench.add_argument(
        "--paths",
        type=_positive_int,
        default=60_000,
        help="curated paths of the cached dataset (default 60,000)",
    )
    serve_bench.set_defaults(run=_bench_serve)
    hostile_bench = _add_bench(
        benches,
        "hostile",
        "links serve under the worst small drawings and clients that send only headers, health "
        "checked every 0.2 s: each answer, health's worst latency, the server's memory growth",
        _bench_hostile,
        ("--paths", 60_000, "curated paths of the dataset served, made once and cached"),
    )
    hostile_bench.add_argument(
        "--root", default=None, help="a curated dataset to serve (default: the cached one)"
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the `links` command `argv` (default: the process's arguments) and return its exit
    status: 0 when it succeeds; 2, with a one-line message on stderr, on bad input or a file
    or store it cannot use."""
    args = build_parser().parse_args(argv)
    try:
        args.run(args)
    except (ValueError, OSError) as exc:
        print(f"links {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
