"""What the `links` commands share: the parser class, the argument types, the options several
commands take, reading the files those options name, and printing a command's result.

Errors a user can cause end as one line on stderr and exit status 2 (`Parser.error` for usage
mistakes, `links_ray.cli.main.main` for the ValueError and OSError a command raises).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from typing import Any, NoReturn

from links_ray.cli import report
from links_ray.engine.inputs import (
    DEFAULT_K,
    MAX_DATASET_JOINTS,
    MAX_K,
    MAX_TRANSMISSION_DEG,
    MIN_JOINTS,
)
from links_ray.interop.curve_files import DEFAULT_CURVE_POINTS
from links_ray.interop.curve_limits import MAX_CURVE_FILE_BYTES


class Parser(argparse.ArgumentParser):
    """Usage mistakes end as one line (the usage is one `--help` away), exit status 2; every
    option's help says its default."""

    def error(self, message: str) -> NoReturn:
        """Exit with status 2 and the message on one line."""
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")

    def add_argument(self, *args: Any, **kwargs: Any) -> argparse.Action:
        """argparse's `add_argument`, its help ending with the default when it has one."""
        action = super().add_argument(*args, **kwargs)
        default = action.default
        # By identity: a default of 0 is worth showing, unlike a flag's False.
        shown = not any(default is nothing for nothing in (None, False, argparse.SUPPRESS))
        if action.option_strings and shown and "default" not in (action.help or ""):
            if isinstance(default, list | tuple):
                default = ",".join(map(str, default))
            action.help = (
                f"{action.help} (default {default})" if action.help else f"default {default}"
            )
        return action


# -- argument types -------------------------------------------------------------------------


def int_at_least(minimum: int, name: str) -> Callable[[str], int]:
    """An argparse type: an integer >= `minimum`, refused in words otherwise."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be a {name} integer, got {text}")
        return value

    return parse


positive_int = int_at_least(1, "positive")
non_negative_int = int_at_least(0, "non-negative")


def port(text: str) -> int:
    """An argparse type: a TCP port, 1 to 65535."""
    number = positive_int(text)
    if number > 65535:
        raise argparse.ArgumentTypeError(f"must be a port from 1 to 65535, got {text}")
    return number


def positive_float(text: str) -> float:
    """An argparse type: a positive finite number, refused in words otherwise."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


# -- options several commands take ----------------------------------------------------------


def json_option(
    command: argparse.ArgumentParser, what: str = "the whole result", piped: bool = False
) -> None:
    """`--json`: print `what` as one JSON object instead of the short human summary. With
    `piped`, JSON is also the default when the output is not a terminal, and `--table`
    asks for the summary anyway."""
    command.add_argument("--json", action="store_true", help=f"print {what} as one JSON object")
    if piped:
        command.add_argument(
            "--table",
            action="store_true",
            help="print the short summary even when the output is not a terminal "
            "(default: JSON then, as scripts read it)",
        )


def tables(args: argparse.Namespace) -> dict:
    """`--tables` as the library takes it; absent, the library's default (the paper's set)."""
    return {} if args.tables is None else {"tables": args.tables}


def max_joints_option(command: argparse.ArgumentParser) -> None:
    """`--max-joints J`, as retrieve and synthesize take it."""
    command.add_argument(
        "--max-joints",
        type=int,
        default=None,
        metavar="J",
        help="only mechanisms whose reduced mechanism (the joints the path needs) has at most "
        f"J joints ({MIN_JOINTS}-{MAX_DATASET_JOINTS}, default: any)",
    )


def query_arguments(
    command: argparse.ArgumentParser, curve_help: str = "", min_transmission: float = 0.0
) -> None:
    """The dataset root, the drawn points' file or a drawing's curve, k, and the least
    transmission angle (default `min_transmission`), as retrieve and synthesize take them."""
    command.add_argument("root", help="dataset root: a folder or s3://...")
    source = command.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--points", metavar="FILE", help='JSON file: [[x, y], ...] or {"points": [...]}'
    )
    source.add_argument(
        "--curve",
        metavar="FILE[#ID]",
        help="a curve in a drawing: .svg (a path or shape, #ID its id, else the first; y up), "
        ".dxf (an LWPOLYLINE, POLYLINE or SPLINE, #ID its layer, else the first), .csv (x,y "
        f"lines) or .json, sampled evenly to {DEFAULT_CURVE_POINTS} points{curve_help}",
    )
    command.add_argument(
        "-k",
        type=positive_int,
        default=DEFAULT_K,
        help=f"results (1-{MAX_K}, default {DEFAULT_K})",
    )
    command.add_argument(
        "--min-transmission",
        type=float,
        default=min_transmission,
        metavar="DEG",
        help="only mechanisms whose least transmission angle is at least DEG degrees "
        f"(0-{MAX_TRANSMISSION_DEG:g}, default {min_transmission:g}"
        + (": all)" if min_transmission == 0 else ")"),
    )


# -- the files options name -----------------------------------------------------------------


def query_points(args: argparse.Namespace) -> tuple[object, bool]:
    """The query's points and whether they close: `--points` as they are (closed), or the
    curve of `--curve` sampled evenly."""
    from links_ray.interop.curve_files import read_curve, read_points

    if args.points is not None:
        return read_points(args.points), True
    curve = read_curve(args.curve)
    return curve.points, curve.closed


def json_file(path: str | None, option: str) -> object:
    """The JSON value in the file an option names (None without one); ValueError naming the
    option and the file if it cannot be read."""
    if path is None:
        return None
    try:
        with open(path, "rb") as stream:
            data = stream.read(MAX_CURVE_FILE_BYTES + 1)
        if len(data) > MAX_CURVE_FILE_BYTES:
            raise ValueError(f"{option} {path}: larger than {MAX_CURVE_FILE_BYTES:,} bytes")
        return json.loads(data)
    except OSError as exc:
        raise ValueError(f"{option} {path}: {exc.strerror or exc}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{option} {path}: not JSON ({exc})") from None


# -- the result -----------------------------------------------------------------------------


def print_result(args: argparse.Namespace, result: dict, formatted: Callable[[dict], str]) -> None:
    """A command's result: one JSON object with --json, else the human-readable table; for
    a command registered with `json_option(..., piped=True)` (`retrieve`, whose output scripts
    read as JSON), JSON also when the output is not a terminal, unless --table."""
    table = getattr(args, "table", None)
    piped = table is not None and not table and not sys.stdout.isatty()
    report.emit(result, formatted, args.json or piped)
