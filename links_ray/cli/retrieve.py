"""`links retrieve ROOT --points FILE | --curve FILE`: the mechanisms whose paths best match a
drawn curve, from the root's retrieval index, offline."""

from __future__ import annotations

import argparse
import time

from links_ray.cli import report
from links_ray.cli.arguments import (
    json_option,
    max_joints_option,
    print_result,
    query_arguments,
    query_points,
)
from links_ray.cli.kernels import note_compiling
from links_ray.engine.inputs import as_max_joints


def add_command(commands: argparse._SubParsersAction) -> None:
    """Register `links retrieve` on the `links` command's subparsers."""
    retrieve = commands.add_parser(
        "retrieve", help="find mechanisms whose path matches the points in FILE (offline)"
    )
    query_arguments(retrieve)
    max_joints_option(retrieve)
    json_option(retrieve, "the results (points and placed mechanisms included)", piped=True)
    retrieve.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """`links retrieve`: check the query, open the index, retrieve, print the results."""
    from links_ray.search.index import RetrievalIndex

    points, _ = query_points(args)
    as_max_joints(args.max_joints)  # before the index loads
    note_compiling("retrieve")
    index = RetrievalIndex.open(args.root)
    start = time.perf_counter()
    results = index.retrieve(
        points, k=args.k, min_transmission=args.min_transmission, max_joints=args.max_joints
    )
    took_ms = (time.perf_counter() - start) * 1e3
    print_result(args, {"results": results, "took_ms": took_ms}, report.format_retrieve)
