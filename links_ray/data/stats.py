"""What a dataset holds, beside the paper's own figures (`links stats`).

Counts per table and joint count, paths per mechanism, the shares of circles and arcs before
and after curation, the distribution of the mechanisms' least transmission angles, candidates
tried per valid mechanism by joint count (from the run when it used the paper's
rejection sampler, otherwise measured here on a sample of topologies), and the throughput the
runs recorded. Reads only small columns; no Ray.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from links_ray.data.commit import committed_shards
from links_ray.data.dataset import open_table
from links_ray.data.pathset import arc_circle_counts, path_shares
from links_ray.data.schemas import CURATION_TABLES, TABLE_NAMES
from links_ray.data.store import META, Store
from links_ray.engine.mechanism import MAX_DATASET_JOINTS, MIN_DATASET_JOINTS
from links_ray.engine.sampling import measure_candidates_per_valid

#: The paper's figures ("Dataset Curation & Processing", "Scale of Infeasibilities"). Its
#: circle and arc shares add up to its arc-or-circle share: its arcs are the arcs that are not
#: circles. 1.1 billion curves of 100 million mechanisms make 11 paths a mechanism.
PAPER = {
    "paths_per_mechanism": 11,
    "shares": {"circle": 0.34, "arc_not_circle": 0.28, "arc_or_circle": 0.62},
    "candidates_per_valid_mean": ">500",
}
#: Least transmission angles (degrees) whose shares below them `links stats` reports, and
#: the quantiles it reports.
TRANSMISSION_THRESHOLDS = (1, 3, 10, 20)
TRANSMISSION_QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)
#: Width of the histogram's bins, in degrees.
TRANSMISSION_BIN_DEG = 5


def _read(store: Store, table: str, columns: list[str]) -> pa.Table | None:
    """Some columns of a table, or None when the dataset has no such table yet."""
    try:
        return open_table(store, table).to_table(columns=columns)
    except ValueError:
        return None


def _counts(rows: pa.Table | None) -> dict | None:
    if rows is None:
        return None
    by_size = pc.value_counts(rows.column("n_joints")).to_pylist()
    return {
        "rows": len(rows),
        # Keys are strings in JSON; ordered as numbers (8 before 10).
        "by_joint_count": {
            str(c["values"]): c["counts"] for c in sorted(by_size, key=lambda c: c["values"])
        },
    }


def _shares(flags: pa.Table | None) -> dict | None:
    return None if flags is None else _shares_of(len(flags), **arc_circle_counts(flags))


def _shares_of(paths: int, arcs: int, circles: int, both: int) -> dict:
    """The shares of `paths` paths with these counts (`pathset.arc_circle_counts`)."""
    shares = path_shares(paths, arcs, circles, both)
    # The arc share of only the arcs that are not circles too: the paper's arc share (its
    # circle and arc shares add up to its arc-or-circle share).
    arc_not_circle = path_shares(paths, arcs - both, 0, 0)["arc"]
    return {"paths": paths, **shares, "arc_not_circle": arc_not_circle}


def _transmission(angles: pa.Table | None) -> dict | None:
    """The distribution of the mechanisms' least transmission angles, in degrees."""
    if angles is None or len(angles) == 0:
        return None
    degrees = angles.column("min_transmission_deg").to_numpy()
    edges = np.arange(0, 90 + TRANSMISSION_BIN_DEG, TRANSMISSION_BIN_DEG)
    counts, _ = np.histogram(degrees, bins=edges)
    return {
        "mechanisms": len(degrees),
        "quantiles": {
            str(q): float(v)
            for q, v in zip(
                TRANSMISSION_QUANTILES, np.quantile(degrees, TRANSMISSION_QUANTILES), strict=True
            )
        },
        "share_below": {str(t): float(np.mean(degrees < t)) for t in TRANSMISSION_THRESHOLDS},
        "histogram": {"bin_deg": TRANSMISSION_BIN_DEG, "counts": counts.tolist()},
    }


def _made_paths(store: Store) -> tuple[dict | None, dict | None]:
    """The counts and shares of every path curation made, from its markers alone: for a root
    that stores no `paths` table (a lean one), whose curators counted them as they made them."""
    markers = committed_shards(store, "curation").values()
    if not markers or any("arcs" not in marker["stats"] for marker in markers):
        return None, None
    by_size: dict[int, int] = {}
    totals = {"paths": 0, "arcs": 0, "circles": 0, "both": 0}
    for marker in markers:
        size = int(marker["n_joints"])
        by_size[size] = by_size.get(size, 0) + int(marker["stats"]["paths"])
        for key in totals:
            totals[key] += int(marker["stats"][key])
    counts = {
        "rows": totals["paths"],
        "by_joint_count": {str(size): count for size, count in sorted(by_size.items())},
    }
    return counts, _shares_of(**totals)


def dataset_stats(root: str, sample_topologies: int = 3, seed: int = 0) -> dict:
    """The statistics of the dataset at `root` as one JSON-ready dict."""
    store = Store.open(root, writable=False)
    run = store.read_json(f"{META}/summary.json")
    curation = store.read_json(f"{META}/curation_summary.json")
    tables = {
        table: _read(store, table, ["n_joints", "is_arc", "is_circle"])
        if table in CURATION_TABLES
        else _read(store, table, ["n_joints"])
        for table in TABLE_NAMES
    }
    counts = {table: _counts(rows) for table, rows in tables.items()}
    if not any(counts.values()):
        raise ValueError(f"{store.uri} holds no dataset tables")
    shares = {table: _shares(tables[table]) for table in CURATION_TABLES}
    if counts["paths"] is None:
        counts["paths"], shares["paths"] = _made_paths(store)
    paths, mechanisms = counts["paths"], counts["mechanisms"]
    paths_per_mechanism = paths and mechanisms and paths["rows"] / mechanisms["rows"]
    # None for a dataset made before the column existed, too (pyarrow's ValueError).
    angles = _read(store, "mechanisms", ["min_transmission_deg"])

    if run and run["plan"]["sampler"] == "rejection":
        candidates = {
            size: entry["candidates_per_valid"] for size, entry in run["by_joint_count"].items()
        }
        source = "the generation run (rejection sampler)"
    else:
        measured = measure_candidates_per_valid(
            range(MIN_DATASET_JOINTS, MAX_DATASET_JOINTS + 1),
            sample_topologies,
            5,
            np.random.default_rng(seed),
            "rejection",
            max_candidates=200_000,
        )
        candidates = {str(n): entry["candidates_per_valid"] for n, entry in measured.items()}
        source = (
            f"measured here: the rejection sampler on {sample_topologies} random topologies per "
            "joint count, five variants each (the data itself was made by the sequential sampler)"
        )
    return {
        "root": store.uri,
        "counts": counts,
        "paths_per_mechanism": paths_per_mechanism,
        "shares": shares,
        "min_transmission_deg": _transmission(angles),
        "candidates_per_valid": candidates,
        "candidates_per_valid_source": source,
        "throughput": {
            "generation": run
            and {
                "mechanisms_per_second": run["mechanisms_per_second"],
                "valid_per_core_second": run["valid_per_core_second"],
                "workers": run["workers"],
                "sampler": run["plan"]["sampler"],
            },
            "curation": curation
            and {
                "seconds": curation["seconds"],
                "mechanisms_per_core_second": curation["mechanisms_per_core_second"],
            },
        },
        "paper": PAPER,
    }
