"""`links generate --out ROOT --mechanisms N`: valid mechanisms generated on Ray into a dataset
root (`links_ray.cluster.generation`), resumed where a run left off."""

from __future__ import annotations

import argparse
import sys

from links_ray.cli import report
from links_ray.cli.arguments import (
    json_option,
    non_negative_int,
    positive_int,
    print_result,
    tables,
)
from links_ray.cli.kernels import note_compiling
from links_ray.engine.inputs import MAX_TRANSMISSION_DEG
from links_ray.engine.kinematics.topology import TOPOLOGY_RULES


def add_command(commands: argparse._SubParsersAction) -> None:
    """Register `links generate` on the `links` command's subparsers."""
    generate = commands.add_parser(
        "generate", help="generate valid mechanisms on Ray into a folder or s3://bucket/prefix"
    )
    generate.add_argument("--out", required=True, help="dataset root: a folder or s3://...")
    generate.add_argument(
        "--mechanisms",
        type=positive_int,
        required=True,
        help="valid mechanisms the root holds; more than a root holds extends it in place",
    )
    generate.add_argument("--seed", type=non_negative_int, default=0)
    generate.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        help="generator actors (default: one per CPU)",
    )
    generate.add_argument("--sampler", choices=["sequential", "rejection"], default="sequential")
    generate.add_argument(
        "--address", default=None, help="Ray cluster address (default: RAY_ADDRESS or a local one)"
    )
    generate.add_argument(
        "--shard-topologies",
        type=positive_int,
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
    json_option(generate, "the run's summary")
    generate.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """`links generate`: generate what the plan still lacks, then print the run's summary."""
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
        **tables(args),
    )
    if summary.get("nothing_to_do"):
        print(
            f"links generate: nothing to do: {args.out} holds all {args.mechanisms:,} "
            "mechanisms of this plan",
            file=sys.stderr,
        )
    print_result(args, summary, report.format_generate)
