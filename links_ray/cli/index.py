"""`links index ROOT [--shards N] [--paths N --seed S]`: the retrieval index of a curated root
built and saved beside the data (`_links/index/`), in as many partitions as `links serve
--shards N` opens; with `--paths`, over a seeded draw of that many curated paths
(`data.path_draw`)."""

from __future__ import annotations

import argparse
import time

from links_ray.cli import report
from links_ray.cli.arguments import json_option, positive_int, print_result


def add_command(commands: argparse._SubParsersAction) -> None:
    """Register `links index` on the `links` command's subparsers."""
    index_command = commands.add_parser(
        "index",
        help="build and save the retrieval index of a curated root (in partitions with --shards)",
    )
    index_command.add_argument("root", help="dataset root: a folder or s3://...")
    index_command.add_argument(
        "--shards",
        type=positive_int,
        default=None,
        help="save the index split into N partitions, as `links serve --shards N` opens it "
        "(default: one index)",
    )
    index_command.add_argument(
        "--paths",
        type=positive_int,
        default=None,
        help="index only a seeded draw of this many curated paths (all of them when the root "
        "holds fewer), saved apart from the full index",
    )
    index_command.add_argument(
        "--seed",
        type=int,
        default=0,
        help="the seed of the draw of --paths (default 0): the same seed, the same paths",
    )
    index_command.add_argument(
        "--rebuild",
        action="store_true",
        help="build every part again, even one saved from the same curated shards",
    )
    json_option(index_command, "the summary, with each part's paths and seconds")
    index_command.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """`links index`: build (or find saved) each part, check it was saved, print the summary."""
    from links_ray.data.commit import committed_files
    from links_ray.data.path_draw import DrawnPaths, PathDraw
    from links_ray.data.store import Store
    from links_ray.search.cache import INDEX_FOLDER, cache_folder
    from links_ray.search.index import RetrievalIndex
    from links_ray.serve.app import check_root  # imports Ray Serve: only when asked for

    parts = args.shards or 1
    draw = None if args.paths is None else PathDraw(args.paths, args.seed)
    check_root(args.root, args.shards)  # what `links serve --shards` would refuse, at once
    # Opened for writing: a root whose keys cannot save the index fails here, not after the
    # builds (`RetrievalIndex.open` on a read-only root builds in memory and saves nothing).
    # Its requests are tried as often as curation's, to ride out a store's brief refusals
    # over a long build.
    store = Store.open(args.root, attempts=10)
    start = time.perf_counter()
    # The draw is of the whole curated set: found once, whatever the parts.
    drawn = None if draw is None else DrawnPaths.of(store, committed_files(store, "curated"), draw)
    made = []
    for part in range(parts):
        began = time.perf_counter()
        index = RetrievalIndex.open(store, rebuild=args.rebuild, part=part, parts=parts, draw=drawn)
        folder = cache_folder(part, parts, draw)
        saved = store.read_json(f"{folder}/current.json") or {}
        if saved.get("fingerprint") != index.fingerprint or saved.get("rows") != len(index):
            raise OSError(
                f"{store.uri}: part {part} of {parts} of the index was built but not saved "
                f"under {store.uri}/{folder}/"
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
        "folder": f"{store.uri}/{INDEX_FOLDER}" + ("" if draw is None else f"/{draw.name}"),
        "draw": None if draw is None else {"paths": draw.paths, "seed": draw.seed},
        "by_part": made,
    }
    print_result(args, summary, report.format_index)
