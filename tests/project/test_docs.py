"""The documentation site builds without a warning, and no page names a `links` command or
option, or an HTTP route, that the code does not have.

The build is `mkdocs build --strict`: a dead link or anchor, a page left out of the nav or a
docstring mkdocstrings cannot read fails it. Pages are scanned for what they name in code:
`links <command> ... --option` in a shell block or a code span, a lone `--option` span, and
`/api/...` routes (with their method where one is written before them) anywhere.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType

import pytest

from tests.support.needs import need_module

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / "docs"

#: Fenced blocks whose lines are shell commands (or a console's, prompts and output).
SHELL_BLOCKS = {"", "bash", "sh", "shell", "console", "shell-session", "zsh", "text"}
FENCE = re.compile(r"^\s*(`{3,}|~{3,})\s*([\w-]*)")
SPAN = re.compile(r"(`+)(.+?)\1")
#: `links` as the command: at the start, after a prompt, a separator or a space.
INVOCATION = re.compile(r"(?:^|(?<=[\s;&|($]))links\s+(?P<rest>.*)$")
#: Where one command in a line ends: a separator or a shell comment.
COMMAND_END = re.compile(r"\s(?:&&|\|\||[|;#])|[;)]")
OPTION = re.compile(r"^--?[A-Za-z][\w-]*")
WORD = re.compile(r"^[a-z][a-z0-9-]*$")
#: A command of some program: a word first (a prompt before it), then arguments.
OTHER_PROGRAM = re.compile(r"^\s*(?:\$\s+)?[A-Za-z][\w.-]*\s")
LONE_OPTION = re.compile(r"^(--[a-z][a-z0-9-]*)(?:[ =]\S+)?$")
_HOST = r"(?:https?://[\w.-]+(?::\d+)?|\b[\w.-]+:\d+)"
ROUTE = rf"(?:{_HOST}|(?<![\w./-]))(/api/[\w{{}}-]+(?:/[\w{{}}-]+)*)"
ROUTE_MENTION = re.compile(ROUTE)
METHOD_ROUTE = re.compile(rf"\b(GET|POST|PUT|PATCH|DELETE|HEAD)\s+{ROUTE}")


def load_hooks() -> ModuleType:
    """docs/hooks/reference_pages.py, the site's hook, loaded as MkDocs loads it (its own
    folder importable while it runs): it is where the CLI parser and the OpenAPI document
    are taken from."""
    folder = DOCS / "hooks"
    spec = importlib.util.spec_from_file_location("reference_pages", folder / "reference_pages.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    saved = sys.path.copy()
    sys.path.insert(0, str(folder))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path[:] = saved
    return module


HOOKS = load_hooks()


@dataclass
class Names:
    """What a page may name: the `links` parser, the routes and their methods."""

    parser: argparse.ArgumentParser
    routes: dict[str, set[str]]
    all_options: set[str] = field(default_factory=set)

    def __post_init__(self) -> None:
        def walk(parser: argparse.ArgumentParser) -> Iterator[str]:
            yield from subparser_options(parser)
            for sub in subparsers(parser).values():
                yield from walk(sub)

        self.all_options = set(walk(self.parser))


def subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The subcommands of `parser` by name."""
    return {name: sub for name, _, sub in HOOKS.reference_cli.subcommands(parser)}


def subparser_options(parser: argparse.ArgumentParser) -> set[str]:
    """The option strings `parser` itself takes."""
    return HOOKS.reference_cli.option_strings(parser)


def code_units(markdown: str) -> Iterator[tuple[int, str, bool]]:
    """(line number, code, is a shell line) of each piece of code in `markdown`: every line of
    a fenced block (joined over a trailing backslash) and every code span of a paragraph
    (which may wrap over lines)."""
    lines = markdown.splitlines()
    fence: str | None = None
    shell = False
    pending = ""
    paragraph: list[tuple[int, str]] = []

    def spans() -> Iterator[tuple[int, str, bool]]:
        if paragraph:
            text = " ".join(line for _, line in paragraph)
            for match in SPAN.finditer(text):
                yield paragraph[0][0], match.group(2).strip(), False
            paragraph.clear()

    for number, line in enumerate(lines, 1):
        opened = FENCE.match(line)
        if fence is None and opened:
            yield from spans()
            fence, shell = opened.group(1), opened.group(2).lower() in SHELL_BLOCKS
            continue
        if fence is not None:
            if line.strip().startswith(fence) and not line.strip().strip(fence[0]):
                fence = None
                continue
            if shell:
                pending = f"{pending} {line.strip()}" if pending else line.strip()
                if pending.endswith("\\"):
                    pending = pending[:-1]
                    continue
                yield number, pending, True
                pending = ""
            continue
        if line.strip():
            paragraph.append((number, line))
        else:
            yield from spans()
    yield from spans()


def command_problems(code: str, names: Names) -> tuple[int, list[str]]:
    """(commands checked, what is wrong) of each `links ...` command in one piece of code."""
    checked, problems = 0, []
    for found in INVOCATION.finditer(code):
        rest = COMMAND_END.split(found.group("rest"), maxsplit=1)[0]
        words = rest.split()
        parser, prog = names.parser, "links"
        while words and WORD.match(words[0]) and subparsers(parser):
            choices = subparsers(parser)
            if words[0] not in choices:
                problems.append(f"`{prog} {words[0]}`: {prog} has no command {words[0]}")
                break
            parser, prog = choices[words[0]], f"{prog} {words[0]}"
            words = words[1:]
        else:
            if words and not OPTION.match(words[0]) and subparsers(parser):
                continue  # a placeholder (`links <command>`), or output, not a command
            checked += 1
            known = subparser_options(parser)
            for word in words:
                option = OPTION.match(word.lstrip("[("))  # `[--seed S]` in a synopsis
                if option and option.group(0) not in known:
                    problems.append(f"`{prog} {option.group(0)}`: {prog} has no such option")
    return checked, problems


def other_tools_options(pages: dict[str, str]) -> set[str]:
    """Options written in commands of other programs (`ray start --head`): a lone span
    naming one of them is not about `links`."""
    options = set()
    for text in pages.values():
        for _, code, _shell in code_units(text):
            for command in re.split(r"&&|\|\||[|;]", INVOCATION.sub("", code)):
                if OTHER_PROGRAM.match(command):
                    options.update(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", command))
    return options


def route_problems(text: str, names: Names) -> tuple[int, list[str]]:
    """(routes checked, what is wrong) of every `/api/...` route `text` names."""
    patterns = {
        path: re.compile(re.sub(r"\\{\w+\\}", r"[^/]+", re.escape(path))) for path in names.routes
    }

    def known(route: str) -> str | None:
        for path, pattern in patterns.items():
            if route == path or pattern.fullmatch(route):
                return path
        return None

    problems = []
    mentions = [match.group(1).rstrip("/") for match in ROUTE_MENTION.finditer(text)]
    problems += [f"{route}: the app has no such route" for route in mentions if not known(route)]
    for match in METHOD_ROUTE.finditer(text):
        method, route = match.group(1), match.group(2).rstrip("/")
        path = known(route)
        if path is not None and method not in names.routes[path]:
            problems.append(f"{method} {route}: it answers {', '.join(sorted(names.routes[path]))}")
    return len(mentions), problems


def page_problems(pages: dict[str, str], names: Names) -> tuple[int, list[str]]:
    """(names checked, `page:line: what is wrong`) over `pages` (name to Markdown)."""
    checked, problems = 0, []
    others = other_tools_options(pages) - names.all_options
    for page, text in pages.items():
        for number, code, _shell in code_units(text):
            count, wrong = command_problems(code, names)
            lone = LONE_OPTION.match(code)
            if lone and not INVOCATION.search(code):
                count += 1
                if lone.group(1) not in names.all_options | others:
                    wrong.append(f"`{lone.group(1)}`: no links command has this option")
            checked += count
            problems += [f"{page}:{number}: {problem}" for problem in wrong]
        count, wrong = route_problems(text, names)
        checked += count
        problems += [f"{page}: {problem}" for problem in wrong]
    return checked, problems


def site_pages() -> dict[str, str]:
    """The README and every Markdown page of docs/, by path from the repository root."""
    paths = [REPO / "README.md", *sorted(DOCS.rglob("*.md"))]
    return {str(path.relative_to(REPO)): path.read_text(encoding="utf-8") for path in paths}


@pytest.fixture(scope="module")
def names() -> Names:
    return Names(HOOKS.cli_parser(), HOOKS.reference_http.routes(HOOKS.openapi_document()))


def test_pages_name_only_commands_options_and_routes_the_code_has(names: Names) -> None:
    checked, problems = page_problems(site_pages(), names)
    assert not problems, "\n".join(problems)
    assert checked >= 10, f"only {checked} commands, options and routes found to check"


PLANTED = """
```bash
links generate --out links-data --mechanizms 5
links serve links-data --shards 2 \\
    --replicaz 2
```

Run `links frobnicate --fast`, or `links bench retreive`. With `links synthesize` pass
`--sead 3`; `links stats ROOT [--plotz DIR]`. Ask `POST /api/retreive`, or `GET /api/simulate`, or
http://127.0.0.1:8000/api/nothing.
"""

CLEAN = """
```bash
links generate --out links-data --mechanisms 5 --seed 0
links serve links-data --shards 2 \\
    --replicas 2  # --replicas R for more
ray job submit --address http://head:8265 -- links curate s3://b/p --workers 4
ray start --head
links bench retrieve --reuse-index --json | jq .recall
```

```console
$ links generate --out d --mechanisms 10
links generate: nothing to do: d holds all 10 mechanisms
```

```python
for links in chains:
    links_ray.load("links-data", "mechanisms")
```

The four links move; `links <command> --help` prints the options, `links --version` the version.
`links-ray` is on PyPI, `links_ray.load` reads tables, `--head` starts a head, `--seed 1`
draws again, `--min-transmission DEG`, `links stats ROOT [--plots DIR] [--json]`,
`links retrieve ROOT [--json \\| --table]`.
`POST /api/retrieve` at http://127.0.0.1:8000/api/retrieve, `GET /api/limits`, `/api/...`,
links_ray/serve/http/asgi/x.
"""


def test_a_planted_option_command_or_route_is_named(names: Names) -> None:
    checked, problems = page_problems({"clean.md": CLEAN}, names)
    assert not problems, "\n".join(problems)
    assert checked >= 13  # commands, lone options and routes in CLEAN, all seen

    _, problems = page_problems({"planted.md": PLANTED}, names)
    expected = [
        "planted.md:3: `links generate --mechanizms`: links generate has no such option",
        "planted.md:5: `links serve --replicaz`: links serve has no such option",
        "planted.md:8: `links frobnicate`: links has no command frobnicate",
        "planted.md:8: `links bench retreive`: links bench has no command retreive",
        "planted.md:8: `--sead`: no links command has this option",
        "planted.md:8: `links stats --plotz`: links stats has no such option",
        "planted.md: /api/retreive: the app has no such route",
        "planted.md: /api/nothing: the app has no such route",
        "planted.md: GET /api/simulate: it answers POST",
    ]
    assert sorted(problems) == sorted(expected)


@pytest.fixture(scope="module")
def mkdocs() -> None:
    need_module("mkdocs", "pip install '.[docs]'")
    need_module("material", "pip install '.[docs]' (mkdocs-material)")
    need_module("mkdocstrings_handlers.python", "pip install '.[docs]' (mkdocstrings[python])")


def build(config: Path, site: Path) -> subprocess.CompletedProcess[str]:
    """`mkdocs build --strict` of `config` into `site`."""
    # The theme's notice about its future is printed on every build, not logged as a warning.
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    command = [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(config)]
    return subprocess.run(
        [*command, "--site-dir", str(site)],
        capture_output=True,
        text=True,
        env=env,
        cwd=config.parent,
        timeout=900,
        check=False,
    )


def test_the_site_builds_strict_with_the_reference_pages(
    mkdocs: None, names: Names, tmp_path: Path
) -> None:
    done = build(REPO / "mkdocs.yml", tmp_path / "site")
    output = done.stdout + done.stderr
    assert done.returncode == 0, output
    assert "WARNING" not in output, output
    cli = (tmp_path / "site" / "reference" / "cli" / "index.html").read_text()
    for prog, parser in all_commands(names.parser, "links"):
        assert f'id="{prog.replace(" ", "-")}"' in cli, f"no section for {prog}"
        for option in subparser_options(parser) - {"-h", "--help"}:
            assert f"<code>{option}</code>" in cli, f"{prog} {option} missing"
    http = (tmp_path / "site" / "reference" / "http" / "index.html").read_text()
    for path, methods in names.routes.items():
        for method in methods:
            assert f"{method} {path}" in http, f"no section for {method} {path}"
    python = (tmp_path / "site" / "reference" / "python" / "index.html").read_text()
    for name in ("load", "search.index.RetrievalIndex", "engine.synthesis.pipeline.synthesize"):
        assert f'id="links_ray.{name}"' in python, f"no section for links_ray.{name}"


def all_commands(
    parser: argparse.ArgumentParser, prog: str
) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """(`links generate`, its parser) for every command and subcommand under `parser`."""
    for name, sub in subparsers(parser).items():
        yield f"{prog} {name}", sub
        yield from all_commands(sub, f"{prog} {name}")


def test_a_dead_link_a_dead_anchor_or_a_stale_generated_page_fails_the_build(
    mkdocs: None, tmp_path: Path
) -> None:
    shutil.copy(REPO / "mkdocs.yml", tmp_path / "mkdocs.yml")
    shutil.copytree(DOCS, tmp_path / "docs", ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / "links_ray").symlink_to(REPO / "links_ray")  # mkdocs.yml's paths and watch
    index = tmp_path / "docs" / "index.md"
    index.write_text(
        index.read_text()
        + "\n[gone](guides/no-such-page.md) and [no section](reference/cli.md#links-frobnicate)\n"
    )
    done = build(tmp_path / "mkdocs.yml", tmp_path / "site")
    output = done.stdout + done.stderr
    assert done.returncode != 0, output
    assert "guides/no-such-page.md" in output, output
    assert "links-frobnicate" in output, output

    index.write_text(index.read_text().split("\n[gone]")[0])
    (tmp_path / "docs" / "reference" / "cli.md").write_text("# Command line\n")
    done = build(tmp_path / "mkdocs.yml", tmp_path / "site")
    output = done.stdout + done.stderr
    assert done.returncode != 0, output
    assert "docs/reference/cli.md is written at build time" in output, output


#: A Markdown link's target: `[text](target)` or `[text](target#anchor)`.
LINK = re.compile(r"\]\((?P<target>[^)\s#]*)(?:#[^)\s]*)?\)")


def dead_links(markdown: str, folder: Path) -> list[str]:
    """The relative link targets in `markdown` that name no file or folder under `folder`."""
    dead = []
    for match in LINK.finditer(markdown):
        target = match["target"]
        if target and "://" not in target and not target.startswith("mailto:"):
            if not (folder / target).exists():
                dead.append(target)
    return dead


def test_the_readme_links_only_to_files_the_repository_has() -> None:
    """The README is read on its own (no site build checks it): each relative link names a
    file in the repository, so no link points at a page the site writes only when built."""
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    assert len(LINK.findall(readme)) >= 10
    assert dead_links(readme, REPO) == []
    assert dead_links("[a](docs/guides/none.md) [b](docs/index.md#x)", REPO) == [
        "docs/guides/none.md"
    ]


def test_the_changelog_names_the_version_the_package_reports() -> None:
    """CHANGELOG.md's newest release is the version pyproject.toml, `links --version` (through
    links_ray.__version__) and CITATION.cff give; releases are listed newest first."""
    import tomllib

    import links_ray

    releases = re.findall(
        r"^## (\d+)\.(\d+)\.(\d+) - \d{4}-\d{2}-\d{2}$", (REPO / "CHANGELOG.md").read_text(), re.M
    )
    assert releases, "CHANGELOG.md lists no release as '## X.Y.Z - YYYY-MM-DD'"
    versions = [tuple(int(part) for part in release) for release in releases]
    assert versions == sorted(versions, reverse=True), versions
    newest = ".".join(releases[0])
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    cited = re.search(r"^version: (\S+)$", (REPO / "CITATION.cff").read_text(), re.M)
    assert (project, links_ray.__version__, cited and cited.group(1)) == (newest, newest, newest)
