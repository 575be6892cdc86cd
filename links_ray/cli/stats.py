"""`links stats ROOT [--plots DIR]`: a dataset's statistics (`links_ray.data.stats`), and its
figures as PNG (`links_ray.cli.figures`)."""

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
        "--sample-topologies",
        type=positive_int,
        default=3,
        help="topologies per joint count when candidates per valid must be measured here",
    )
    json_option(stats, "every statistic", piped=True)
    stats.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """`links stats`: measure, draw the figures if asked, print every statistic."""
    from links_ray.data.stats import dataset_stats

    stats = dataset_stats(args.root, sample_topologies=args.sample_topologies)
    if args.plots:
        from links_ray.cli.figures import write_figures

        stats["plots"] = write_figures(args.root, args.plots, stats)
    print_result(args, stats, report.format_stats)
