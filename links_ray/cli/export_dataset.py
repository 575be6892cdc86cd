"""`links export-dataset ROOT --out DIR`: a dataset in the LINKS release layout, as numpy
chunks (`links_ray.data.release`)."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable

from links_ray.data.release import DEFAULT_CHUNK_MECHANISMS, export_release
from links_ray.data.splits import SPLITS


def add_command(commands: argparse._SubParsersAction, count: Callable[[str], int]) -> None:
    """Add `export-dataset` to the `links` subcommands; `count` parses a positive integer."""
    command = commands.add_parser(
        "export-dataset",
        help="write a dataset as numpy arrays in the LINKS release layout, chunk by chunk",
    )
    command.add_argument("root", help="dataset root: a folder or s3://...")
    command.add_argument("--out", required=True, help="a new or empty local folder")
    command.add_argument(
        "--chunk-size",
        type=count,
        default=DEFAULT_CHUNK_MECHANISMS,
        metavar="N",
        help="mechanisms per chunk, each chunk of one joint count",
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
    """`links export-dataset`: write the release and print its summary (or its manifest as
    JSON with --json)."""
    manifest = export_release(args.root, args.out, chunk_size=args.chunk_size, split=args.split)
    if args.json:
        print(json.dumps(manifest))
        return
    made = f", {manifest['resimulated']:,} simulated again" if manifest["resimulated"] else ""
    print(
        f"{manifest['mechanisms']:,} mechanisms{made}, {manifest['normalized']:,} normalized "
        f"and {manifest['curated']:,} curated curves in {len(manifest['chunks'])} chunks: "
        f"{args.out}"
    )
