"""The command-line reference page, written from the `links` argument parser.

Every command has a `## links <command>` heading (anchor `#links-<command>`); `links bench`'s
benchmarks have `### links bench <name>`. Each lists its usage and every argument with its value
and help, where the parser's own help already states each option's default.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator

from reference_text import text

HEADER = """# Command line

The `links` command. This page is written from the command's own argument parser each time the
site is built, so it says what `links <command> --help` says. Every command also takes
`-h`/`--help`; `links --version` prints the installed version.
"""

#: Columns of the usage blocks.
USAGE_WIDTH = 88


def subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(name, one-line help, parser) of each subcommand of `parser`, in the parser's order;
    empty when it has none."""
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {choice.dest: choice.help or "" for choice in action._choices_actions}
            for name, sub in action.choices.items():
                found.append((name, helps.get(name, ""), sub))
    return found


def option_strings(parser: argparse.ArgumentParser) -> set[str]:
    """Every option string `parser` itself accepts (`-h` and `--help` included)."""
    return {string for action in parser._actions for string in action.option_strings}


def _help(action: argparse.Action, prog: str) -> str:
    """The action's help as `--help` prints it (`%(default)s` and the like expanded)."""
    if not action.help:
        return ""
    params = {k: v for k, v in vars(action).items() if v is not argparse.SUPPRESS}
    params["prog"] = prog
    if params.get("choices") is not None:
        params["choices"] = ", ".join(map(str, params["choices"]))
    return action.help % params


def _value(action: argparse.Action) -> str:
    """What the argument takes: its choices, its metavar, or nothing for a flag."""
    if action.nargs == 0:
        return "flag"
    if action.choices is not None:
        return " or ".join(f"`{choice}`" for choice in action.choices)
    metavar = action.metavar or (action.dest if not action.option_strings else action.dest.upper())
    return f"`{metavar}`"


def _usage(parser: argparse.ArgumentParser) -> str:
    """The usage line as `--help` prints it, wrapped at a fixed width rather than the
    terminal's, so that the page does not depend on where it is built."""
    formatter = parser.formatter_class(prog=parser.prog, width=USAGE_WIDTH)
    formatter.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups)
    return formatter.format_help().strip()


def _arguments(parser: argparse.ArgumentParser) -> Iterator[str]:
    rows = []
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction | argparse._SubParsersAction):
            continue
        name = ", ".join(f"`{s}`" for s in action.option_strings) or f"`{action.dest}`"
        help_text = _help(action, parser.prog)
        if action.required or not action.option_strings:
            help_text = f"{help_text} (required)" if help_text else "required"
        rows.append(f"| {name} | {_value(action)} | {text(help_text) or '-'} |")
    if rows:
        yield "| argument | value | meaning |"
        yield "|---|---|---|"
        yield from rows
        yield ""


def _table(commands: list[tuple[str, str, argparse.ArgumentParser]]) -> Iterator[str]:
    """A table of `commands`, each linked to its section."""
    yield "| command | what it does |"
    yield "|---|---|"
    for _, summary, parser in commands:
        yield f"| [`{parser.prog}`](#{parser.prog.replace(' ', '-')}) | {text(summary)} |"
    yield ""


def _command(summary: str, parser: argparse.ArgumentParser, level: int) -> Iterator[str]:
    """A command's section at heading `level`, then its subcommands' one level down."""
    yield f"{'#' * level} {parser.prog}"
    yield ""
    if summary:
        yield text(summary[0].upper() + summary[1:]) + "."
        yield ""
    yield "```text"
    yield _usage(parser)
    yield "```"
    yield ""
    yield from _arguments(parser)
    children = subcommands(parser)
    if children:
        yield from _table(children)
        for _, child_summary, child_parser in children:
            yield from _command(child_summary, child_parser, level + 1)


def cli_page(parser: argparse.ArgumentParser) -> str:
    """The page's Markdown: every command and subcommand of `parser` (`prog` "links")."""
    commands = subcommands(parser)
    lines = [HEADER, *_table(commands)]
    for _, summary, sub in commands:
        lines.extend(_command(summary, sub, 2))
    return "\n".join(lines)
