"""What the `links` commands print: a short table for a person by default, the whole result as
one JSON object with `--json`.

Every command's human output is made here, from the same dict `--json` prints, so numbers are
rounded one way and joint counts ordered one way (8, 9, ..., 20) everywhere.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from links_ray.data.store import META

#: The shares of `links stats`, in the order and words a person reads them.
_SHARE_NAMES = {
    "circle": "circles",
    "arc_not_circle": "arcs, not circles",
    "arc_or_circle": "either",
    "both": "both",
}


def emit(result: dict, human: Callable[[dict], str], as_json: bool) -> None:
    """Print `result` as one JSON object with `--json`, else as `human` renders it."""
    print(json.dumps(result, default=_jsonable) if as_json else human(result))


def _jsonable(value: object) -> object:
    """`json.dumps` fallback for numpy arrays and scalars: where a retrieval result's arrays
    become lists, the numbers `tolist` gives (those of a list made before printing)."""
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


# -- numbers --------------------------------------------------------------------------------


def count(value: int | None) -> str:
    """An integer with thousands separators; `-` for none."""
    return "-" if value is None else f"{value:,}"


def number(value: float | None) -> str:
    """A measured number to about three significant figures (1.07, 30,876, 0.0132), as many
    decimals for every number of one magnitude; `-` for none, `inf` for a search that found
    nothing."""
    if value is None:
        return "-"
    if not math.isfinite(value):
        return "inf" if value > 0 else str(value)
    size = abs(value)
    if size >= 100:
        return f"{value:,.0f}"
    if size >= 10:
        return f"{value:.1f}"
    if size >= 1:
        return f"{value:.2f}"
    return f"{value:.3g}"


def percent(share: float | None) -> str:
    """A share of 1 as a percentage with one decimal."""
    return "-" if share is None else f"{100 * share:.1f}%"


def duration(seconds: float) -> str:
    """Seconds as a person reads them: 850 ms, 4.2 s, 3 min 20 s."""
    if seconds < 1:
        return f"{seconds * 1e3:.0f} ms"
    if seconds < 120:
        return f"{seconds:.1f} s"
    return f"{seconds // 60:.0f} min {seconds % 60:.0f} s"


def by_joints(mapping: Mapping[str, Any] | Mapping[int, Any]) -> list[tuple[int, Any]]:
    """A per-joint-count mapping (JSON keys are strings) as (joints, value) pairs, 8 before 10."""
    return sorted((int(n), value) for n, value in mapping.items())


def table(header: Sequence[str], rows: Sequence[Sequence[object]], names: int = 1) -> str:
    """Columns padded to their widest cell, two spaces apart: the first `names` columns
    left-aligned (they name the row), the others right-aligned (they hold numbers)."""
    cells = [[str(cell) for cell in row] for row in [header, *rows]]
    widths = [max(len(row[i]) for row in cells) for i in range(len(header))]
    return "\n".join(
        "  ".join(
            cell.ljust(width) if i < names else cell.rjust(width)
            for i, (cell, width) in enumerate(zip(row, widths, strict=True))
        ).rstrip()
        for row in cells
    )


def _more(where: str) -> str:
    return f"(--json for everything; the full summary is also in {where})"


def _summary_file(root: str, name: str) -> str:
    return f"{root.rstrip('/')}/{META}/{name}"


# -- links generate -------------------------------------------------------------------------


def format_generate(summary: dict) -> str:
    """Rows written, throughput, and per joint count the topologies, mechanisms and search."""
    plan, rows = summary["plan"], summary["rows"]
    written = ", ".join(f"{table} {count(n)}" for table, n in rows.items())
    state = "complete" if summary["complete"] else "incomplete: run the same command again"
    sizes = by_joints(summary["by_joint_count"])
    body = [
        [n, count(s["topologies"]), count(s["mechanisms"]), number(s["candidates_per_valid"])]
        + ([count(s["below_transmission"])] if plan["min_transmission_deg"] else [])
        + [count(s["abandoned"])]
        for n, s in sizes
    ]
    header = ["joints", "topologies", "mechanisms", "candidates/valid"]
    header += ["below transmission"] if plan["min_transmission_deg"] else []
    header += ["abandoned"]
    lines = [
        f"{summary['out']}: {count(rows['mechanisms'])} mechanisms ({state}); {written}",
        f"{plan['sampler']} sampler, {plan['topology_rules']} topologies, seed {plan['seed']}, "
        f"{summary['shards']} shards",
    ]
    if summary.get("seconds") is not None and summary.get("mechanisms_per_second"):
        lines.append(
            f"{duration(summary['seconds'])} on {summary['workers']} workers: "
            f"{number(summary['mechanisms_per_second'])} mechanisms per second, "
            f"{number(summary['valid_per_core_second'])} per core-second"
        )
    lines += [
        "",
        table(header, body, names=0),
        f"candidates/valid: {summary['candidates_per_valid_meaning']}",
        _more(_summary_file(summary["out"], "summary.json")),
    ]
    return "\n".join(lines)


# -- links curate ---------------------------------------------------------------------------


def format_curate(summary: dict) -> str:
    """Paths made and kept, and the shares of arcs and circles among them."""
    paths = summary["paths"]
    shares = summary["shares"]
    lines = [
        f"{summary['out']}: {count(summary['mechanisms'])} mechanisms made "
        f"{count(paths)} paths, {count(summary['curated'])} curated "
        f"({percent(summary['curated'] / paths if paths else None)}); "
        f"wrote {', '.join(summary['tables'])}",
        f"{summary['shards_this_run']} of {summary['shards']} shards curated by this run",
    ]
    if summary.get("resimulated"):
        lines[-1] += f" ({count(summary['resimulated'])} mechanisms simulated again)"
    if summary["shards_this_run"]:
        lines.append(
            f"{duration(summary['seconds'])}: "
            f"{number(summary['mechanisms_per_core_second'])} mechanisms per core-second"
        )
    lines += [
        "",
        table(
            ["among all paths", "paths", "share"],
            [
                ["circles", count(summary["circles"]), percent(shares["circle"])],
                ["arcs", count(summary["arcs"]), percent(shares["arc"])],
                ["either", "", percent(shares["arc_or_circle"])],
                ["both", count(summary["both"]), percent(shares["both"])],
            ],
        ),
        _more(_summary_file(summary["out"], "curation_summary.json")),
    ]
    return "\n".join(lines)


# -- links index ----------------------------------------------------------------------------


def format_index(summary: dict) -> str:
    """One line: the paths indexed, in how many parts, how many built (the rest were saved
    already), where, and how long it took."""
    parts = summary["parts"]
    built = summary["built"]
    saved = "" if built == parts else f", {parts - built} already saved"
    draw = summary.get("draw")
    drawn = "" if draw is None else f" (the draw of seed {draw['seed']})"
    return (
        f"{summary['root']}: {count(summary['paths'])} paths{drawn} indexed in {parts} "
        f"part{'s' if parts != 1 else ''} ({built} built{saved}) under {summary['folder']}/ "
        f"in {duration(summary['seconds'])}"
    )


# -- links stats ----------------------------------------------------------------------------


def format_stats(stats: dict) -> str:
    """Rows by joint count, shares beside the paper's, transmission angles, candidates per
    valid mechanism (a column when known, else the line saying why not) and throughput."""
    counts = stats["counts"]
    tables = [name for name, entry in counts.items() if entry]
    columns = {
        name: {n: count(rows) for n, rows in by_joints(counts[name]["by_joint_count"])}
        for name in tables
    }
    missing = dict.fromkeys(tables, count(0))
    totals = [count(counts[name]["rows"]) for name in tables]
    candidates = stats["candidates_per_valid"]
    if candidates is not None:  # None when not measured: no column, the line below says why
        columns["candidates/valid"] = {n: number(value) for n, value in by_joints(candidates)}
        missing["candidates/valid"] = number(None)
        totals.append("")
    sizes = sorted({n for column in columns.values() for n in column})
    rows = [[n, *(column.get(n, missing[name]) for name, column in columns.items())] for n in sizes]
    rows.append(["all", *totals])
    lines = [
        f"{stats['root']}: "
        + ", ".join(f"{count(counts[name]['rows'])} {name}" for name in tables),
        "",
        table(["joints", *columns], rows, names=0),
        f"candidates/valid: {stats['candidates_per_valid_source']}",
    ]
    shares = stats["shares"]
    paper = stats["paper"]
    if shares.get("paths") or shares.get("curated"):
        header = ["share of paths"]
        header += ["all paths"] if shares.get("paths") else []
        header += ["paper"]
        header += ["curated"] if shares.get("curated") else []
        body = []
        for key, name in _SHARE_NAMES.items():
            row = [name]
            row += [percent(shares["paths"][key])] if shares.get("paths") else []
            row += [percent(paper["shares"].get(key))]
            row += [percent(shares["curated"][key])] if shares.get("curated") else []
            body.append(row)
        lines += ["", table(header, body)]
        if stats.get("paths_per_mechanism"):
            lines.append(
                f"paths per mechanism: {number(stats['paths_per_mechanism'])} "
                f"(paper {paper['paths_per_mechanism']})"
            )
    angles = stats.get("min_transmission_deg")
    if angles:
        quantiles, below = angles["quantiles"], angles["share_below"]
        lines += [
            "",
            f"least transmission angle of {count(angles['mechanisms'])} mechanisms: median "
            f"{number(quantiles['0.5'])} deg, 5% below {number(quantiles['0.05'])}, 95% below "
            f"{number(quantiles['0.95'])}",
            "within "
            + ", ".join(f"{t} deg: {percent(share)}" for t, share in by_joints(below))
            + " of a dead centre",
        ]
    throughput = stats.get("throughput") or {}
    made = throughput.get("generation")
    if made and made.get("mechanisms_per_second"):
        lines.append(
            f"generation: {number(made['mechanisms_per_second'])} mechanisms per second on "
            f"{made['workers']} workers ({made['sampler']} sampler)"
        )
    curated = throughput.get("curation")
    if curated and curated.get("mechanisms_per_core_second"):
        lines.append(
            f"curation: {number(curated['mechanisms_per_core_second'])} mechanisms per core-second"
        )
    if stats.get("plots"):
        lines.append("figures: " + ", ".join(stats["plots"]))
    lines.append("(--json for everything)")
    return "\n".join(lines)


# -- links retrieve, links synthesize -------------------------------------------------------


def format_retrieve(answer: dict) -> str:
    """Each match: its path, mechanism, joint count and chamfer distance."""
    results = answer["results"]
    rows = [
        [
            rank,
            result["path_id"],
            result["mechanism_id"],
            result["joint"],
            len(result["mechanism"]["node_types"]),
            number(result.get("min_transmission_deg")),
            f"{result['chamfer']:.4f}",
        ]
        for rank, result in enumerate(results, 1)
    ]
    return "\n".join(
        [
            f"{len(results)} paths in {duration(answer['took_ms'] / 1e3)} (chamfer between the "
            "normalized curves, best first)",
            table(
                ["rank", "path", "mechanism", "joint", "joints", "transmission", "chamfer"],
                rows,
            ),
            "(transmission: the mechanism's least transmission angle in degrees; --json for the "
            "paths' points and the mechanisms placed on the drawing)",
        ]
    )


def format_synthesize(answer: dict) -> str:
    """Each mechanism: its chamfer on the drawing, before and after refinement, whether
    refinement moved it (why not, when not), and where on the crank's turn a partial stroke
    lies."""
    results = answer["results"]
    if answer.get("unmet"):
        unmet = answer["unmet"]
        return (
            f"no mechanism keeps the constraints: the nearest misses {unmet['constraint']} by "
            f"{unmet['by']:.4g}"
        )
    timed = any("timed_error" in result for result in results)
    rows = []
    for rank, result in enumerate(results, 1):
        interval = result["interval"]
        where = (
            f"{interval['start_deg']:.1f} to {interval['start_deg'] + interval['sweep_deg']:.1f}"
            if interval
            else "full turn"
        )
        rows.append(
            [
                rank,
                f"{result['chamfer']:.4f}",
                f"{result['retrieved_chamfer']:.4f}",
                *([f"{result['timed_error']:.4f}"] if timed else []),
                "yes" if result["refined"] else UNREFINED_WORDS[result["why"]][0],
                len(result["mechanism"]["node_types"]),
                result["mechanism_joint"],
                result["path_id"],
                where,
            ]
        )
    return "\n".join(
        [
            f"{len(results)} mechanisms in {duration(answer['took_ms'] / 1e3)} (chamfer / the "
            "drawing's longest chord, best first)",
            table(
                [
                    "rank",
                    "chamfer",
                    "retrieved",
                    *(["timed"] if timed else []),
                    "refined",
                    "joints",
                    "joint",
                    "from path",
                    "crank deg",
                ],
                rows,
            ),
            synthesize_footnote(results),
        ]
    )


#: A result's `why` (not refined), as the table says it, and what the footnote says of it.
UNREFINED_WORDS = {
    "no_time": ("no (no time)", "no time: the budget was spent before its first iteration"),
    "no_step": ("no (no step)", "no step: none tried lowered its chamfer and kept it valid"),
    "cannot_refine": ("no (refused)", "refused: refinement cannot take it as retrieved"),
    "stopped": ("no (stopped)", "stopped: the work was called off first"),
}


def synthesize_footnote(results: list[dict]) -> str:
    """The table's last line: why results are unrefined, when any is, and where the rest is."""
    why = sorted({result["why"] for result in results if not result["refined"]})
    said = [UNREFINED_WORDS[reason][1] for reason in why]
    return f"({'; '.join([*said, '--json for the mechanisms'])})"


# -- links demo -----------------------------------------------------------------------------


def format_demo(summary: dict) -> str:
    """Mechanisms written, by joint count."""
    sizes = by_joints(summary["joint_counts"])
    return "\n".join(
        [
            f"{summary['out']}: {count(summary['mechanisms'])} mechanisms of "
            f"{count(summary['topologies'])} topologies ({summary['sampler']} sampler, "
            f"{number(summary['candidates_per_valid'])} candidates per valid) in "
            f"{duration(summary['seconds'])}",
            table(["joints", "mechanisms"], [[n, count(m)] for n, m in sizes], names=0),
            f"(--json for the summary; the mechanisms are in {summary['out']}/mechanisms.jsonl)",
        ]
    )
