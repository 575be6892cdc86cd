"""The `links` command line: the commands, each a module with `add_command` (its parser) and
`run` (what it does), listed here in the order `links --help` shows them. `links bench` is the
benchmarks' own room (`links_ray.bench`), loaded only when the command line asks for it.

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
)
#: What `links --help` says of `links bench`, without loading the benchmarks.
BENCH_HELP = "benchmarks"


def build_parser(bench: bool = True) -> argparse.ArgumentParser:
    """The `links` command line: every command, its options and the function that runs it
    (`args.run`). The site's CLI reference is written from it. With `bench` false, `links bench`
    is only named (its benchmarks are not loaded): for every other command."""
    parser = Parser(prog="links", description="LINKS: planar linkage mechanisms and their paths.")
    parser.add_argument("--version", action="version", version=f"links-ray {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    for command in COMMANDS:
        command.add_command(commands)
    if bench:
        from links_ray.bench import command as bench_command

        bench_command.add_command(commands, BENCH_HELP)
    else:
        commands.add_parser("bench", help=BENCH_HELP)
    return parser


def asks_for_bench(argv: Sequence[str]) -> bool:
    """Whether `argv` is a `links bench` command line: its first word that is not an option."""
    words = [word for word in argv if not word.startswith("-")]
    return bool(words) and words[0] == "bench"


def main(argv: Sequence[str] | None = None) -> int:
    """Run the `links` command `argv` (default: the process's arguments) and return its exit
    status: 0 when it succeeds; 2, with a one-line message on stderr, on bad input or a file
    or store it cannot use."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(bench=asks_for_bench(argv)).parse_args(argv)
    try:
        args.run(args)
    except (ValueError, OSError) as exc:
        print(f"links {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
