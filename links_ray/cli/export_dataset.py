"""`links export-dataset ROOT --out DIR [--format numpy|release]`: a dataset in the LINKS
release layout, as numpy chunks or as the release's own pickled files
(`links_ray.release.exporter`)."""

from __future__ import annotations

import argparse
import json

from links_ray.cli.arguments import positive_int
from links_ray.data.splits import SPLITS
from links_ray.release.exporter import DEFAULT_CHUNK_MECHANISMS, EXPORT_FORMATS, export_release
from links_ray.release.pickled_export import DEFAULT_RELEASE_BATCH


def add_command(commands: argparse._SubParsersAction) -> None:
    """Add `export-dataset` to the `links` subcommands."""
    command = commands.add_parser(
        "export-dataset",
        help="write a dataset in the LINKS release layout: numpy chunks or the release's files",
    )
    command.add_argument("root", help="dataset root: a folder or s3://...")
    command.add_argument("--out", required=True, help="a new or empty local folder")
    command.add_argument(
        "--format",
        choices=EXPORT_FORMATS,
        default="numpy",
        help="numpy: chunks of numpy arrays of one joint count each, with a manifest; release: "
        "the release's four pickled files (dataset, simulation_dataset, normalized_dataset, "
        "curated_dataset) that code written for it reads unchanged",
    )
    command.add_argument(
        "--chunk-size",
        type=positive_int,
        default=None,
        metavar="N",
        help=f"mechanisms per chunk (default {DEFAULT_CHUNK_MECHANISMS:,}, each of one joint "
        f"count) or per release batch (default {DEFAULT_RELEASE_BATCH:,}, joint counts mixed)",
    )
    command.add_argument(
        "--split",
        choices=SPLITS,
        default=None,
        help="only this split's topologies (80/10/10 by topology; default: every mechanism)",
    )
    command.add_argument("--json", action="store_true", help="print the manifest as JSON")
    command.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """`links export-dataset`: write the export and print its summary (or its manifest, or the
    release files' summary, as JSON with --json)."""
    manifest = export_release(
        args.root, args.out, chunk_size=args.chunk_size, split=args.split, format=args.format
    )
    if args.json:
        print(json.dumps(manifest))
        return
    if args.format == "release":
        locked = f", {manifest['locked']:,} locking at its angles" if manifest["locked"] else ""
        print(
            f"{manifest['mechanisms']:,} mechanisms{locked}, {manifest['normalized']:,} "
            f"normalized and {manifest['curated']:,} curated curves in "
            f"{len(manifest['batches'])} batches of the release's files: {args.out}"
        )
        return
    made = f", {manifest['resimulated']:,} simulated again" if manifest["resimulated"] else ""
    print(
        f"{manifest['mechanisms']:,} mechanisms{made}, {manifest['normalized']:,} normalized "
        f"and {manifest['curated']:,} curated curves in {len(manifest['chunks'])} chunks: "
        f"{args.out}"
    )
