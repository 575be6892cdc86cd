"""`links curate ROOT`: the Ray Data pass that writes a root's normalized paths and its curated
subset (`links_ray.cluster.curation`)."""

from __future__ import annotations

import argparse

from links_ray.cli import report
from links_ray.cli.arguments import (
    json_option,
    non_negative_int,
    positive_int,
    print_result,
    tables,
)
from links_ray.cli.kernels import note_compiling
from links_ray.data.schemas import PATH_STORES


def add_command(commands: argparse._SubParsersAction) -> None:
    """Register `links curate` on the `links` command's subparsers."""
    curate = commands.add_parser(
        "curate", help="Ray Data pass: normalized paths and the curated subset, with statistics"
    )
    curate.add_argument("root", help="dataset root: a folder or s3://...")
    curate.add_argument("--seed", type=non_negative_int, default=0, help="curation draw seed")
    curate.add_argument("--workers", type=positive_int, default=None)
    curate.add_argument("--address", default=None, help="Ray cluster address")
    curate.add_argument(
        "--tables",
        default=None,
        metavar="TABLES",
        help="tables to write, comma-separated: paths, curated or both (default both; with "
        "--store ids, curated)",
    )
    curate.add_argument(
        "--store",
        choices=PATH_STORES,
        default="points",
        help="points: the paths with their points (default); ids: ids and flags only, a lean "
        "root whose readers derive the points from the mechanisms, bit for bit",
    )
    json_option(curate, "the pass's summary")
    curate.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """`links curate`: curate what is not curated yet, then print the pass's summary."""
    from links_ray.cluster.curation import curate  # imports Ray: only when asked for

    summary = curate(
        args.root,
        seed=args.seed,
        workers=args.workers,
        address=args.address,
        starting=lambda: note_compiling("curate"),
        path_store=args.store,
        **tables(args),
    )
    print_result(args, summary, report.format_curate)
