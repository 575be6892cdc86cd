"""The `links` command line: the commands, each a module with `add_command` (its parser) and
`run` (what it does), listed here in the order `links --help` shows them.

Errors a user can cause end as one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from links_ray import __version__
from links_ray.cli import (
    curate,
    demo,
    export,
    export_dataset,
    generate,
    import_release,
    index,
    retrieve,
    serve,
    stats,
    synthesize,
    warm,
)
from links_ray.cli.arguments import Parser
from links_ray.cli.bench import command as bench

#: Every `links` command, in the order of `links --help`.
COMMANDS = (
    demo,
    warm,
    generate,
    curate,
    index,
    stats,
    serve,
    retrieve,
    synthesize,
    export,
    export_dataset,
    import_release,
    bench,
)


def build_parser() -> argparse.ArgumentParser:
    """The `links` command line: every command, its options and the function that runs it
    (`args.run`). The site's CLI reference is written from it."""
    parser = Parser(prog="links", description="LINKS: planar linkage mechanisms and their paths.")
    parser.add_argument("--version", action="version", version=f"links-ray {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    for command in COMMANDS:
        command.add_command(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the `links` command `argv` (default: the process's arguments) and return its exit
    status: 0 when it succeeds; 2, with a one-line message on stderr, on bad input or a file
    or store it cannot use."""
    args = build_parser().parse_args(argv)
    try:
        args.run(args)
    except (ValueError, OSError) as exc:
        print(f"links {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
