"""The RayJobs of deploy/ against the `links` command line they run, without a cluster.

Every RayJob's entrypoint runs real `links` commands, parsed by the command line's own parser,
chained inside `bash -c` so that the submitter's shell runs none of them, with && alone so that
a failed step ends the job; and for every root a RayService serves, one job generates it and
one curates it and then saves its index split as the RayService serves it.

Each check returns the problems it finds, and `test_a_planted_mistake_is_found` shows each one
finding a mistake planted in a copy (tests/support/manifests.py holds the parsed manifests and
the helpers the test_deploy_*.py files share).
"""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from collections.abc import Callable
from typing import Any

import pytest
import yaml

from tests.support.manifests import (
    MANIFESTS,
    Check,
    Manifests,
    Plant,
    edit,
    objects,
    planted_copy,
    the_app,
)

#: Shell operators in an entrypoint, as `shlex` splits them with punctuation_chars.
SHELL_OPERATORS = {"&&", "||", ";", "|", "&", ";;", "(", ")", "<", ">", ">>", "<<"}


def shell_words(text: str) -> list[str]:
    """`text` split as a POSIX shell splits it, operators as words of their own."""
    lexer = shlex.shlex(text, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    return list(lexer)


def entrypoint_commands(entrypoint: str, env: dict[str, str]) -> tuple[list[list[str]], list[str]]:
    """The commands a RayJob's entrypoint runs, each as its words ($NAME and ${NAME} replaced
    by `env`), and the problems with it.

    KubeRay's submitter runs `ray job submit ... -- ENTRYPOINT ; ...` in a shell, so a bare
    operator in ENTRYPOINT would split the submission there and run the rest in the
    submitter's pod: a chain must be one argument of `bash -c` (or `sh -c`), joined by `&&`
    only, so that a failed step ends the job."""
    problems: list[str] = []

    def expand(word: str) -> str:
        def value(found: re.Match[str]) -> str:
            name = found[1] or found[2]
            if name not in env:
                problems.append(f"${name} is set nowhere in the head's env")
            return env.get(name, "")

        return re.sub(r"\$\{(\w+)\}|\$(\w+)", value, word)

    words = shell_words(entrypoint)
    if SHELL_OPERATORS & set(words):
        problems.append(
            f"{entrypoint!r}: the submitter's shell would run what follows "
            f"{sorted(SHELL_OPERATORS & set(words))} itself; chain commands in bash -c '...'"
        )
        return [], problems
    if words[:2] in (["bash", "-c"], ["sh", "-c"]) and len(words) == 3:
        words = shell_words(words[2])
    commands: list[list[str]] = [[]]
    for word in words:
        if word == "&&":
            commands.append([])
        elif word in SHELL_OPERATORS:
            problems.append(f"{entrypoint!r}: chain commands with && only, not {word!r}")
        else:
            commands[-1].append(expand(word))
    return [command for command in commands if command], problems


def parse_links(words: list[str]) -> tuple[Any, str | None]:
    """`links ARGS` parsed by the command line's own parser: (its namespace, None), or (None,
    the parser's complaint)."""
    from links_ray.cli.main import build_parser

    if words[:1] != ["links"]:
        return None, f"{shlex.join(words)!r} is not a links command"
    complaint = io.StringIO()
    try:
        with contextlib.redirect_stderr(complaint), contextlib.redirect_stdout(io.StringIO()):
            return build_parser().parse_args(words[1:]), None
    except SystemExit:
        return None, f"{shlex.join(words)!r}: {complaint.getvalue().strip()}"


def job_steps(manifests: Manifests) -> tuple[dict[str, list[Any]], list[str]]:
    """The `links` commands of each RayJob, parsed, in order; and the problems found."""
    steps: dict[str, list[Any]] = {}
    problems = []
    for where, job in objects(manifests, "RayJob"):
        head = job["spec"]["rayClusterSpec"]["headGroupSpec"]["template"]["spec"]
        env = {
            item["name"]: str(item["value"])
            for container in head["containers"]
            for item in container.get("env", [])
            if "value" in item
        }
        commands, found = entrypoint_commands(job["spec"]["entrypoint"], env)
        problems += [f"{where}: {problem}" for problem in found]
        steps[where] = []
        for words in commands:
            parsed, complaint = parse_links(words)
            if complaint:
                problems.append(f"{where}: {complaint}")
            else:
                steps[where].append(parsed)
    return steps, problems


def root_of(parsed: Any) -> str:
    """The dataset root a parsed `links generate`, `curate` or `index` works on."""
    return (parsed.out if parsed.command == "generate" else parsed.root).rstrip("/")


# -- the checks -----------------------------------------------------------------------------


def job_problems(manifests: Manifests) -> list[str]:
    """Every RayJob entrypoint runs real `links` commands, and for every root a RayService
    serves, one job generates it and one curates it and then saves its index split as the
    RayService serves it."""
    steps, problems = job_steps(manifests)
    for where, service in objects(manifests, "RayService"):
        args = the_app(yaml.safe_load(service["spec"]["serveConfigV2"])).get("args", {})
        root = str(args["root"]).rstrip("/")
        shards = args.get("shards")
        if not any(
            step.command == "generate" and root_of(step) == root
            for done in steps.values()
            for step in done
        ):
            problems.append(f"{where}: no RayJob generates {root}")
        indexed = False
        for done in steps.values():
            for place, step in enumerate(done):
                if step.command == "index" and root_of(step) == root and step.shards == shards:
                    curated = any(
                        s.command == "curate" and root_of(s) == root for s in done[:place]
                    )
                    indexed = indexed or curated
        if not indexed:
            split = f"--shards {shards}" if shards else "no --shards"
            problems.append(
                f"{where}: no RayJob curates {root}, then runs links index with {split}"
            )
    return problems


# -- the tests ------------------------------------------------------------------------------


def test_jobs_run_links_commands_that_make_every_served_root() -> None:
    steps, _ = job_steps(MANIFESTS)
    commands = {step.command for done in steps.values() for step in done}
    assert {"generate", "curate", "index"} <= commands
    assert job_problems(MANIFESTS) == []


# -- each check finds a planted mistake -----------------------------------------------------


INDEX_JOB = "kuberay/rayjob-index.yaml"


def entrypoint(text: str) -> Callable[[dict], None]:
    def change(job: dict) -> None:
        job["spec"]["entrypoint"] = text

    return change


#: (check, the mistake planted, a phrase of the problem it must report).
PLANTED: list[tuple[Check, Plant, str]] = [
    (
        job_problems,
        lambda m: edit(
            m, INDEX_JOB, "links-index", entrypoint("bash -c 'links indx s3://links/dataset'")
        ),
        "invalid choice: 'indx'",
    ),
    (
        job_problems,
        lambda m: edit(
            m,
            INDEX_JOB,
            "links-index",
            entrypoint(
                "links curate s3://links/dataset && links index s3://links/dataset --shards 32"
            ),
        ),
        "the submitter's shell would run",
    ),
    (
        job_problems,
        lambda m: edit(
            m,
            INDEX_JOB,
            "links-index",
            entrypoint(
                "bash -c 'links curate s3://links/dataset && "
                "links index s3://links/dataset --shards 16'"
            ),
        ),
        "then runs links index with --shards 32",
    ),
    (
        job_problems,
        lambda m: edit(
            m,
            INDEX_JOB,
            "links-index",
            entrypoint("bash -c 'links index s3://links/dataset --shards 32'"),
        ),
        "no RayJob curates s3://links/dataset",
    ),
]


@pytest.mark.parametrize(
    ("check", "plant", "phrase"), PLANTED, ids=[phrase for _, _, phrase in PLANTED]
)
def test_a_planted_mistake_is_found(check: Check, plant: Plant, phrase: str) -> None:
    found = check(planted_copy(plant))
    assert any(phrase in problem for problem in found), found
