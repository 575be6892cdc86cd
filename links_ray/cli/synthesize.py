"""`links synthesize ROOT --points FILE | --curve FILE`: mechanisms retrieved for a drawn curve
and refined onto it (`links_ray.engine.synthesis.pipeline`), offline."""

from __future__ import annotations

import argparse
import time

from links_ray.cli import report
from links_ray.cli.arguments import (
    json_file,
    json_option,
    max_joints_option,
    non_negative_int,
    positive_float,
    positive_int,
    print_result,
    query_arguments,
    query_points,
)
from links_ray.cli.kernels import note_compiling
from links_ray.engine.synthesis.options import (
    DEFAULT_SYNTHESIS_SECONDS,
    DEFAULT_SYNTHESIS_TRANSMISSION_DEG,
    MAX_SYNTHESIS_ITERATIONS,
    MAX_SYNTHESIS_SECONDS,
    SynthesisOptions,
)


def add_command(commands: argparse._SubParsersAction) -> None:
    """Register `links synthesize` on the `links` command's subparsers."""
    synthesize = commands.add_parser(
        "synthesize",
        help="find mechanisms for the curve in FILE and refine them onto it (offline)",
    )
    query_arguments(
        synthesize,
        "; an open curve is matched as a stroke (as with --partial)",
        DEFAULT_SYNTHESIS_TRANSMISSION_DEG,
    )
    synthesize.add_argument(
        "--seconds",
        type=positive_float,
        default=None,
        help=f"time budget, retrieval included (at most {MAX_SYNTHESIS_SECONDS:g}, "
        f"default {DEFAULT_SYNTHESIS_SECONDS:g})",
    )
    synthesize.add_argument(
        "--iterations",
        type=positive_int,
        default=None,
        help=f"counted work instead of a time budget: about this many refinement iterations "
        f"(at most {MAX_SYNTHESIS_ITERATIONS:,}); equal inputs give equal answers",
    )
    synthesize.add_argument(
        "--seed",
        type=non_negative_int,
        default=0,
        help="seed of the random restarts (default 0)",
    )
    synthesize.add_argument(
        "--partial",
        action="store_true",
        help="the points are an open stroke: match them to part of a crank turn (the default "
        "for an open --curve)",
    )
    max_joints_option(synthesize)
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
        'xmax, ymax], "footprint": [...], "max_link_ratio": R, "min_link": L, "max_link": L, '
        '"max_layers": N} (any of them); every result keeps them',
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
    json_option(synthesize, "the results (mechanisms included)")
    synthesize.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """`links synthesize`: check every option before the index loads, synthesize, print the
    results (and what was unmet)."""
    from links_ray.engine.synthesis.pipeline import synthesize
    from links_ray.engine.synthesis.target import as_target
    from links_ray.engine.synthesis.warm import warm_synthesis
    from links_ray.search.index import RetrievalIndex

    points, closed = query_points(args)
    partial = args.partial or not closed
    # Checked once, before the index loads:
    options = SynthesisOptions(
        k=args.k,
        seconds=args.seconds,
        partial=partial,
        min_transmission_deg=args.min_transmission,
        max_joints=args.max_joints,
        front=args.front,
        constraints=json_file(args.constraints, "--constraints"),
        timing=args.timing if args.timing in (None, True) else json_file(args.timing, "--timing"),
        seed=args.seed,
        iterations=args.iterations,
    )
    points = options.drawing(points)
    note_compiling("synthesize")
    index = RetrievalIndex.open(args.root)
    # Compiled (or loaded) before the budget's clock starts, and before `took_ms`'s.
    warm_synthesis(as_target(points, partial), options, index)
    start = time.perf_counter()
    results = synthesize(index, points, options=options)
    took_ms = (time.perf_counter() - start) * 1e3
    answer = {"results": list(results), "took_ms": took_ms}
    if results.unmet is not None:
        answer["unmet"] = results.unmet
    print_result(args, answer, report.format_synthesize)
