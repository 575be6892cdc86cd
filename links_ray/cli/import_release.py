"""`links import-release SRC --out ROOT`: the LINKS release's own files imported into a
links-ray root (`links_ray.release.importer`)."""

from __future__ import annotations

import argparse
import json

from links_ray.release.importer import import_release


def add_command(commands: argparse._SubParsersAction) -> None:
    """Add `import-release` to the `links` subcommands."""
    command = commands.add_parser(
        "import-release",
        help="import the LINKS release's pickled files (dataset, simulation_dataset, "
        "curated_dataset) into a dataset root, checked by links-ray's solver",
    )
    command.add_argument("src", help="the folder holding the release's files: a folder or s3://")
    command.add_argument("--out", required=True, help="dataset root: a folder or s3://...")
    command.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the curated choice when the release has no curated_dataset",
    )
    command.add_argument("--json", action="store_true", help="print the summary as JSON")
    command.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """`links import-release`: import, then print the summary (as JSON with --json)."""
    summary = import_release(args.src, args.out, seed=args.seed)
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
