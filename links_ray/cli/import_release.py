"""`links import-release SRC --out ROOT`: the LINKS release's own files imported into a
links-ray root (`links_ray.release.importer`), its shards committed by actors on Ray
(`links_ray.cluster.release_import`)."""

from __future__ import annotations

import argparse
import functools
import json

from links_ray.cli.arguments import non_negative_int, positive_int
from links_ray.data.schemas import PATH_STORES
from links_ray.release.importer import import_release


def add_command(commands: argparse._SubParsersAction) -> None:
    """Add `import-release` to the `links` subcommands."""
    command = commands.add_parser(
        "import-release",
        help="import the LINKS release's pickled files (dataset, simulation_dataset, "
        "curated_dataset) into a dataset root on Ray, checked by links-ray's solver",
    )
    command.add_argument("src", help="the folder holding the release's files: a folder or s3://")
    command.add_argument("--out", required=True, help="dataset root: a folder or s3://...")
    command.add_argument(
        "--seed",
        type=non_negative_int,
        default=0,
        help="seed of the curated choice when the release has no curated_dataset",
    )
    command.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        help="import actors (default: one per CPU)",
    )
    command.add_argument(
        "--address", default=None, help="Ray cluster address (default: RAY_ADDRESS or a local one)"
    )
    command.add_argument(
        "--tables",
        default=None,
        metavar="TABLES",
        help="tables to write, comma-separated: mechanisms and any of negatives, paths, curated "
        "(default all four; with --store ids, mechanisms,curated); a resumed import must use "
        "the same",
    )
    command.add_argument(
        "--store",
        choices=PATH_STORES,
        default="points",
        help="points: the path tables with their points (default); ids: ids and flags only, a "
        "lean root (with the default tables, the layout of links generate --tables mechanisms "
        "then links curate --store ids) whose readers derive the points, bit for bit",
    )
    command.add_argument("--json", action="store_true", help="print the summary as JSON")
    command.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """`links import-release`: import on Ray, then print the summary (as JSON with --json)."""
    from links_ray.cluster.release_import import import_on_ray  # imports Ray: only when asked for

    runner = functools.partial(import_on_ray, workers=args.workers, address=args.address)
    summary = import_release(
        args.src,
        args.out,
        seed=args.seed,
        tables=args.tables,
        path_store=args.store,
        runner=runner,
    )
    if args.json:
        print(json.dumps(summary))
        return
    worst = f", worst error {summary['worst_error']:.2g}" if summary["disagreeing"] else ""
    print(
        f"{summary['mechanisms']:,} mechanisms and {summary['negatives']:,} negatives from "
        f"{summary['release_batches']} release batches; against the release's trajectories "
        f"{summary['agreeing']:,} agree, {summary['disagreeing']:,} disagree{worst}, "
        f"{summary['locking_at_release_angles']:,} lock, {summary['unchecked']:,} unchecked; "
        f"{summary['paths']:,} paths, {summary['curated']:,} curated "
        f"(the {'release' if summary['curated_from'] == 'release' else 'seeded'} choice): "
        f"{summary['out']}"
    )
