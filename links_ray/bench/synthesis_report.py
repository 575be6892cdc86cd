"""What `links bench synthesize` reports besides its rows: the curve set's groups by half and
family, the answers' transmission and the fronts' layers summed up, and the bench and its time
dial as Markdown tables (`links_ray.bench.synthesis` measures)."""

from __future__ import annotations

import statistics

import numpy as np

from links_ray.bench.curves.curve_set import HALVES

#: Families grouped in the set's report as `smooth_closed`.
SMOOTH_CLOSED = ("gait", "cam", "random_smooth")


def set_groups(rows: list[dict]) -> list[dict]:
    """Per half (and both, `all`), per family (and `smooth_closed`, and `all`) of the set's
    `rows`: the curves, mean retrieval-only and mean and median refined chamfer, refined /
    retrieved (of the means), and the median and worst seconds."""
    families = sorted({row["family"] for row in rows})
    groups = []
    for half in (*HALVES, "all"):
        in_half = [row for row in rows if half in ("all", row["half"])]
        for family in (*families, "smooth_closed", "all"):
            members = [
                row
                for row in in_half
                if family in ("all", row["family"])
                or (family == "smooth_closed" and row["family"] in SMOOTH_CLOSED)
            ]
            if not members:
                continue
            retrieved = statistics.fmean(row["retrieved"] for row in members)
            refined = [row["refined"] for row in members]
            seconds = [row["seconds"] for row in members]
            dense = [row["dense"] for row in members if row.get("dense") is not None]
            ordered = [row["ordered"] for row in members if row.get("ordered") is not None]
            groups.append(
                {
                    "half": half,
                    "family": family,
                    "curves": len(members),
                    "mean_retrieved": retrieved,
                    "mean_refined": statistics.fmean(refined),
                    "median_refined": statistics.median(refined),
                    "ratio": statistics.fmean(refined) / retrieved,
                    "mean_ordered": statistics.fmean(ordered) if ordered else None,
                    "median_dense": statistics.median(dense) if dense else None,
                    "median_seconds": statistics.median(seconds),
                    "worst_seconds": max(seconds),
                }
            )
    return groups


def quantiles(values: list[float]) -> dict:
    """The least, the 10th percentile and the median of `values`."""
    return {
        "min": min(values),
        "p10": float(np.quantile(values, 0.1)),
        "median": statistics.median(values),
    }


def front_layers(rows: list[dict]) -> dict:
    """What the fronts' answers of `rows` need as kits: layers (mean, worst, the share of
    answers with no plan), of the best answer of each curve too, and the seconds of planning
    them against the seconds of synthesis."""
    answers = [answer for row in rows for answer in row["front"]]
    planned = [answer["layers"] for answer in answers if answer["layers"] is not None]
    best = [min(row["front"], key=lambda answer: answer["chamfer"])["layers"] for row in rows]
    best_planned = [layers for layers in best if layers is not None]
    shares = [row["layer_seconds"] / row["seconds"] for row in rows]
    return {
        "answers": len(answers),
        "no_plan": 1 - len(planned) / len(answers),
        "mean": statistics.fmean(planned) if planned else None,
        "max": max(planned, default=None),
        "best_no_plan": 1 - len(best_planned) / len(best),
        "best_mean": statistics.fmean(best_planned) if best_planned else None,
        "best_max": max(best_planned, default=None),
        "plan_seconds_median": statistics.median(row["layer_seconds"] for row in rows),
        "plan_seconds_max": max(row["layer_seconds"] for row in rows),
        "plan_share_median": statistics.median(shares),
    }


def format_dial(result: dict) -> str:
    """The time dial as a Markdown table: mean (median) refined chamfer at each budget."""
    budgets = [f"{seconds:g}" for seconds in result["budgets_s"]]
    lines = [
        f"Synthesis at {', '.join(budgets)} s a curve over {result['paths']:,} curated paths, "
        f"frames of seed {result['seed']}: mean (median) chamfer / longest chord",
        "",
        "| half | family | curves | " + " | ".join(f"{b} s" for b in budgets) + " |",
        "|---|---|---|" + "---|" * len(budgets),
    ]
    for entry in result["dial"]:
        at = entry["by_budget"]
        cells = [f"{at[b]['mean_refined']:.4f} ({at[b]['median_refined']:.4f})" for b in budgets]
        lines.append(
            f"| {entry['half']} | {entry['family']} | {entry['curves']} | "
            + " | ".join(cells)
            + " |"
        )
    return "\n".join(lines)


def format_synthesize(result: dict) -> str:
    """The bench as a Markdown table."""
    work = (
        f"budget {result['budget_s']:g} s"
        if result["budget_s"] is not None
        else f"{result['iterations']:,} iterations"
    )

    def overrun(value: float | None) -> str:
        return "" if value is None else f"{value:.0f}"

    lines = [
        f"Synthesis over {result['paths']:,} curated paths, {result['points_per_curve']} points "
        f"a curve, {work}, frames of seed {result['seed']} "
        "(chamfer / the drawing's longest chord)",
        "",
        "| curve | retrieval only | refined | refined, ordered | reference (even) | joints "
        "| seconds | overrun ms |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in result["curves"]:
        ordered = "" if row.get("ordered") is None else f"{row['ordered']:.4f}"
        lines.append(
            f"| {row['curve']} | {row['retrieved']:.4f} | {row['refined']:.4f} | {ordered} | "
            f"{row['reference']:.4f} | {row['joints']} | {row['seconds']:.2f} | "
            f"{overrun(row['overrun_ms'])} |"
        )
    lines.append(
        f"| **mean** (median s, worst overrun) | {result['mean_retrieved']:.4f} | "
        f"{result['mean_refined']:.4f} | | {result['mean_reference']:.4f} | | "
        f"{result['median_seconds']:.2f} | {overrun(result['worst_overrun_ms'])} |"
    )
    if result.get("groups"):
        lines += [
            "",
            "| half | family | curves | retrieval only (mean) | refined mean | refined median "
            "| refined / retrieved | ordered mean | dense median | median s | worst s |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]

        def shown(value: float | None) -> str:
            return "" if value is None else f"{value:.4f}"

        lines += [
            f"| {g['half']} | {g['family']} | {g['curves']} | {g['mean_retrieved']:.4f} | "
            f"{g['mean_refined']:.4f} | {g['median_refined']:.4f} | {g['ratio']:.3f} | "
            f"{shown(g['mean_ordered'])} | {shown(g['median_dense'])} | "
            f"{g['median_seconds']:.2f} | {g['worst_seconds']:.2f} |"
            for g in result["groups"]
        ]
    angles = result["transmission_deg"]
    lines += [
        "",
        f"least transmission angle of the answers (floor asked {result['min_transmission']:g}): "
        f"least {angles['min']:.1f}, 10th percentile {angles['p10']:.1f}, "
        f"median {angles['median']:.1f} degrees",
    ]
    layers = result.get("layers")
    if layers:

        def shown(value: float | None) -> str:
            return "none" if value is None else f"{value:.2f}"

        lines.append(
            f"the fronts' {layers['answers']} answers as kits: {layers['no_plan']:.0%} with no "
            f"layer plan, the rest {shown(layers['mean'])} layers on average, at most "
            f"{layers['max']}; the best of each curve {layers['best_no_plan']:.0%} with none, "
            f"{shown(layers['best_mean'])} on average, at most {layers['best_max']}; planning "
            f"a front {layers['plan_seconds_median']:.2f} s (median, worst "
            f"{layers['plan_seconds_max']:.2f} s), {layers['plan_share_median']:.0%} of its "
            "synthesis's time (median)"
        )
    lines += ["", f"refined / retrieval-only: {result['ratio']:.3f}"]
    lines += [f"{goal}: {'yes' if met else 'no'}" for goal, met in result["goals"].items()]
    return "\n".join(lines)
