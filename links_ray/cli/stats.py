"""`links stats ROOT [--json] [--plots DIR] [--measure-candidates N]`: a dataset's statistics
(`links_ray.data.stats`) as a table, or JSON with `--json`, and its figures as PNG
(`links_ray.cli.figures`)."""

from __future__ import annotations

import argparse

from links_ray.cli import report
from links_ray.cli.arguments import json_option, positive_int, print_result


def add_command(commands: argparse._SubParsersAction) -> None:
    """Register `links stats` on the `links` command's subparsers."""
    stats = commands.add_parser("stats", help="dataset statistics, figures as PNG")
    stats.add_argument("root", help="dataset root: a folder or s3://...")
    stats.add_argument("--plots", default=None, help="folder for the PNG figures")
    stats.add_argument(
        "--measure-candidates",
        type=positive_int,
        default=None,
        metavar="N",
        help="measure candidates per valid mechanism: the paper's rejection sampler on N random "
        "topologies per joint count, five variants each (default: not measured; taken from "
        "the generation run when it used the rejection sampler)",
    )
    json_option(stats, "every statistic")
    stats.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """`links stats`: count, measure if asked, draw the figures if asked, print the result."""
    from links_ray.data.stats import dataset_stats

    stats = dataset_stats(args.root, sample_topologies=args.measure_candidates)
    if args.plots:
        from links_ray.cli.figures import write_figures

        stats["plots"] = write_figures(args.root, args.plots, stats)
    print_result(args, stats, report.format_stats)
