"""`links bench NAME`: every benchmark, one table of them, and one runner (the `links` command
line loads this module only for `links bench`).

Each benchmark measures (its module imported only then: several start Ray), its messages kept
off stdout, which is the result's; the result is then printed as a table or, with `--json`, as
one JSON object.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Callable
from dataclasses import dataclass

from links_ray.bench.synthesis import BENCH_SECONDS
from links_ray.cli.arguments import (
    json_option,
    non_negative_int,
    positive_float,
    positive_int,
    print_result,
)
from links_ray.engine.synthesis.options import (
    DEFAULT_SYNTHESIS_SECONDS,
    DEFAULT_SYNTHESIS_TRANSMISSION_DEG,
)

#: What a benchmark measured and how a person reads it.
Measured = tuple[dict, Callable[[dict], str]]


@dataclass(frozen=True)
class Benchmark:
    """`links bench NAME [--json] [SIZE N] ...`: most benchmarks have one size option."""

    name: str
    help: str
    measure: Callable[[argparse.Namespace], Measured]
    size: tuple[str, int, str] | None  # the option, its default and what it counts
    more_arguments: Callable[[argparse.ArgumentParser], None] | None = None


# -- what each benchmark measures -----------------------------------------------------------


def _simulate(args: argparse.Namespace) -> Measured:
    from links_ray.bench import engine

    return engine.bench_simulate(repeats=args.repeats), engine.format_simulate


def _simulate_one(args: argparse.Namespace) -> Measured:
    from links_ray.bench import engine

    return engine.bench_simulate_one(mechanisms=args.mechanisms), engine.format_simulate_one


def _sample(args: argparse.Namespace) -> Measured:
    from links_ray.bench import engine

    return engine.bench_sample(per_joint_count=args.topologies), engine.format_sample


def _generate(args: argparse.Namespace) -> Measured:
    from links_ray.bench import generate  # imports Ray: only when asked for

    result = generate.bench_generate(mechanisms=args.mechanisms, lean=args.lean)
    return result, generate.format_generate


def _generate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--lean",
        action="store_true",
        help="write the mechanisms table alone (a lean run; target 8,000 valid a core-second) "
        "and show where one shard's time goes",
    )


def _retrieve(args: argparse.Namespace) -> Measured:
    from links_ray.bench import retrieve

    result = retrieve.bench_retrieve(
        paths=args.paths, rebuild=not args.reuse_index, root=args.root, seed=args.seed
    )
    return result, retrieve.format_retrieve


def _synthesize(args: argparse.Namespace) -> Measured:
    from links_ray.bench import synthesis, synthesis_report

    if args.design:
        from links_ray.bench import design

        if args.set or args.curve or args.iterations is not None or args.figure or args.dial:
            raise ValueError(
                "--design runs the 8 targets at a time budget: no --set, --curve, "
                "--iterations, --figure or --dial"
            )
        result = design.bench_design(seconds=args.seconds, paths=args.paths, seed=args.seed)
        return result, design.format_design
    if args.dial:
        if args.iterations is not None or args.figure or args.seconds is not None:
            raise ValueError("--dial runs its own budgets: no --seconds, --iterations or --figure")
        result = synthesis.bench_dial(
            paths=args.paths, seed=args.seed, use_set=args.set, only=tuple(args.curve or ())
        )
        return result, synthesis_report.format_dial
    result = synthesis.bench_synthesize(
        seconds=args.seconds,
        paths=args.paths,
        seed=args.seed,
        figure=args.figure,
        iterations=args.iterations,
        use_set=args.set,
        only=tuple(args.curve or ()),
        min_transmission=args.min_transmission,
        front=args.front,
    )
    return result, synthesis_report.format_synthesize


def _kit(args: argparse.Namespace) -> Measured:
    from links_ray.bench import kit

    return kit.bench_kit(mechanisms=args.mechanisms, seed=args.seed), kit.format_kit


def _kit_arguments(command: argparse.ArgumentParser) -> None:
    command.add_argument(
        "--seed",
        type=non_negative_int,
        default=0,
        help="seed of the random mechanisms (default 0, the benchmarks page's figures)",
    )


def _import_release(args: argparse.Namespace) -> Measured:
    from links_ray.bench import release

    return release.bench_import(batches=args.batches), release.format_import


def _serve(args: argparse.Namespace) -> Measured:
    from links_ray.bench import serve

    result = serve.bench_serve(
        shards=args.shards,
        seconds=args.seconds,
        clients=args.clients,
        paths=args.paths,
        root=args.root,
        largest_bodies=not args.no_largest_bodies,
    )
    return result, serve.format_serve


def _hostile(args: argparse.Namespace) -> Measured:
    from links_ray.bench import hostile

    measured = hostile.bench_hostile(
        paths=args.paths, root=args.root, fuzz_seconds=args.fuzz_seconds or 0.0
    )
    return measured, hostile.format_hostile


# -- the options beyond the size ------------------------------------------------------------


def _retrieve_arguments(command: argparse.ArgumentParser) -> None:
    command.add_argument(
        "--reuse-index",
        action="store_true",
        help="load the saved index and report its recorded build time instead of rebuilding",
    )
    command.add_argument(
        "--root",
        default=None,
        help="measure the index of a seeded draw of --paths curated paths of this root (a "
        "folder), in process, instead of the benchmark's own dataset",
    )
    command.add_argument(
        "--seed",
        type=non_negative_int,
        default=0,
        help="the seed of the draw with --root (default 0), as `links index --seed`",
    )


def _synthesize_arguments(command: argparse.ArgumentParser) -> None:
    command.add_argument(
        "--seconds",
        type=positive_float,
        default=None,
        help=f"budget per curve (default {BENCH_SECONDS:g}; with --set the synthesis default, "
        f"{DEFAULT_SYNTHESIS_SECONDS:g})",
    )
    command.add_argument(
        "--seed",
        type=non_negative_int,
        default=0,
        help="seed of the curves' random frames (default 0, the benchmarks page's table)",
    )
    command.add_argument(
        "--iterations",
        type=positive_int,
        default=None,
        help="counted work per curve instead of --seconds (the seed seeds the restarts too)",
    )
    command.add_argument(
        "--figure",
        default=None,
        help="also draw every curve, its retrieved path and refined mechanism into this PNG",
    )
    command.add_argument(
        "--set",
        action="store_true",
        help="the curve set of links_ray.bench.curves.curve_set (a tuning and a held-out half) "
        "instead of the 8 targets, reported per half and family; the figure shows the held-out "
        "half (needs the bench extra)",
    )
    command.add_argument(
        "--design",
        action="store_true",
        help="buildable answers instead: per target, the plain best, the front (simplest "
        "first), a pivot region and footprint kept, and the timed error, each at the budget "
        "(default the synthesis default)",
    )
    command.add_argument(
        "--dial",
        action="store_true",
        help="the time dial: the same run at 1, 3, 10 and 30 s a curve, and each family's "
        "mean (median) chamfer at each budget",
    )
    command.add_argument(
        "--curve",
        action="append",
        default=None,
        metavar="NAME",
        help="run only this curve (repeat for several); with --iterations its row is the same "
        "bit for bit as in a run of them all",
    )
    command.add_argument(
        "--min-transmission",
        type=float,
        default=DEFAULT_SYNTHESIS_TRANSMISSION_DEG,
        metavar="DEG",
        help="the least transmission angle the synthesis keeps, as `links synthesize` takes it "
        f"(default {DEFAULT_SYNTHESIS_TRANSMISSION_DEG:g})",
    )
    command.add_argument(
        "--front",
        action="store_true",
        help="answer each curve with the front, and report its answers' layers as kits and "
        "the seconds of planning them",
    )


def _serve_arguments(command: argparse.ArgumentParser) -> None:
    command.add_argument(
        "--shards",
        type=non_negative_int,
        action="append",
        default=None,
        help="partitions to serve with, 0 for one index in the gateway; repeat for several "
        "runs (default: 0, 1 and 2)",
    )
    command.add_argument(
        "--seconds", type=positive_float, default=30.0, help="load per run (default 30)"
    )
    command.add_argument(
        "--clients", type=positive_int, default=32, help="retrieving clients (default 32)"
    )
    command.add_argument(
        "--root",
        default=None,
        help="a curated dataset to serve (default: a cached one of --paths curated paths)",
    )
    command.add_argument(
        "--no-largest-bodies",
        action="store_true",
        help="skip the last run, of clients posting the largest simulations the limits allow",
    )
    command.add_argument(
        "--paths",
        type=positive_int,
        default=60_000,
        help="curated paths of the cached dataset (default 60,000)",
    )


def _hostile_arguments(command: argparse.ArgumentParser) -> None:
    command.add_argument(
        "--root", default=None, help="a curated dataset to serve (default: the cached one)"
    )
    command.add_argument(
        "--fuzz-seconds",
        type=positive_float,
        default=None,
        help="then fuzz the release importer's unpickler this many seconds (default: not at all)",
    )


#: Every benchmark, in the order `links bench --help` lists them.
BENCHMARKS = (
    Benchmark(
        "simulate",
        "the paper's Table 1: 10,000 random mechanisms, 200 steps",
        _simulate,
        ("--repeats", 5, "timed runs of each method"),
    ),
    Benchmark(
        "simulate-one",
        "one mechanism a call: full turns a second of simulate, TopologySimulator, simulate_batch",
        _simulate_one,
        ("--mechanisms", 200, "valid mechanisms (8-20 joints, five per topology)"),
    ),
    Benchmark(
        "sample",
        "position samplers: valid per core-second, candidates per valid",
        _sample,
        ("--topologies", 10, "topologies per joint count"),
    ),
    Benchmark(
        "generate",
        "end-to-end generation on local Ray: valid mechanisms per core-second",
        _generate,
        ("--mechanisms", 50_000, "mechanisms per run"),
        _generate_arguments,
    ),
    Benchmark(
        "retrieve",
        "retrieval latency and recall@3 on a cached curated dataset",
        _retrieve,
        ("--paths", 1_000_000, "curated paths in the index"),
        _retrieve_arguments,
    ),
    Benchmark(
        "synthesize",
        "synthesis of the shipped target curves: retrieval-only and refined chamfer, seconds",
        _synthesize,
        ("--paths", 1_000_000, "curated paths in the index"),
        _synthesize_arguments,
    ),
    Benchmark(
        "kit",
        "random dataset mechanisms as kits at the default sizes: share with no layer plan, "
        "layers, share proven fewest, seconds to plan; by joint count",
        _kit,
        ("--mechanisms", 1000, "valid mechanisms (8-20 joints, five per topology)"),
        _kit_arguments,
    ),
    Benchmark(
        "import-release",
        "the release's pickled files (exported from the bench set, batches of 100,000) "
        "imported: mechanisms per second, peak memory",
        _import_release,
        ("--batches", 2, "release batches of 100,000 mechanisms"),
    ),
    Benchmark(
        "serve",
        "serving under load: retrievals per second, latencies, 503s, by shard count",
        _serve,
        None,  # its --paths comes last, after the load's options
        _serve_arguments,
    ),
    Benchmark(
        "hostile",
        "links serve under the worst small drawings and clients that send only headers, health "
        "checked every 0.2 s: each answer, health's worst latency, the server's memory growth",
        _hostile,
        ("--paths", 60_000, "curated paths of the dataset served, made once and cached"),
        _hostile_arguments,
    ),
)


def add_command(commands: argparse._SubParsersAction, summary: str) -> None:
    """Register `links bench` (`summary` said of it in `links --help`) and each benchmark under it
    on the `links` command's subparsers."""
    bench_parser = commands.add_parser("bench", help=summary)
    benches = bench_parser.add_subparsers(dest="bench", required=True)
    for benchmark in BENCHMARKS:
        command = benches.add_parser(benchmark.name, help=benchmark.help)
        json_option(command)
        if benchmark.size is not None:
            option, default, meaning = benchmark.size
            command.add_argument(
                option, type=positive_int, default=default, help=f"{meaning} (default {default:,})"
            )
        if benchmark.more_arguments is not None:
            benchmark.more_arguments(command)
        command.set_defaults(run=run, benchmark=benchmark)


def run(args: argparse.Namespace) -> None:
    """`links bench NAME`: measure, its messages on stderr, then print the result."""
    with contextlib.redirect_stdout(sys.stderr):
        result, formatted = args.benchmark.measure(args)
    print_result(args, result, formatted)
