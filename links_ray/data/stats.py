"""What a dataset holds, beside the paper's own figures (`links stats`).

Counts per table and joint count, paths per mechanism, the shares of circles and arcs before
and after curation, the distribution of the mechanisms' least transmission angles, candidates
tried per valid mechanism by joint count (from the run when it used the paper's rejection
sampler, measured here only when asked: see `candidates_per_valid`), and the throughput the
runs recorded. No Ray, and memory bounded whatever the size: counts come from the commit
markers, flags and the angles' histogram are counted a file at a time, and only the
mechanisms' least transmission angles are held whole (4 bytes a mechanism, up to twice that
while their array grows, for exact quantiles).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pyarrow as pa

from links_ray.data.commit import TABLE_STAGE, committed_files, committed_shards
from links_ray.data.curation import arc_circle_counts, path_shares
from links_ray.data.schemas import CURATION_TABLES, TABLE_NAMES
from links_ray.data.store import META, Store
from links_ray.engine.kinematics.mechanism import MAX_DATASET_JOINTS, MIN_DATASET_JOINTS
from links_ray.engine.kinematics.sampling import measure_candidates_per_valid

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


def _counts(markers: dict[str, dict[int, dict]], table: str) -> dict | None:
    """A table's rows, in all and by joint count, from its stage's commit markers; None when
    no committed shard holds the table (a marker leaves out a table it wrote no row of)."""
    holding = [m for m in markers[TABLE_STAGE[table]].values() if table in m["rows"]]
    if not holding:
        return None
    by_size: dict[int, int] = {}
    for marker in holding:
        size = int(marker["n_joints"])
        by_size[size] = by_size.get(size, 0) + int(marker["rows"][table])
    return {
        "rows": sum(by_size.values()),
        # Keys are strings in JSON; ordered as numbers (8 before 10).
        "by_joint_count": {str(n): rows for n, rows in sorted(by_size.items()) if rows},
    }


def _file_columns(
    store: Store, markers: dict[str, dict[int, dict]], table: str, columns: list[str]
) -> Iterator[pa.Table]:
    """Some columns of a table's committed files, a file at a time: a pyarrow dataset scan
    of the same columns holds memory that grows with the table."""
    for relative in committed_files(store, table, markers[TABLE_STAGE[table]]):
        yield store.read_parquet(relative, columns=columns)


def _shares(
    store: Store, markers: dict[str, dict[int, dict]], table: str, counted: dict | None
) -> dict | None:
    """The circle and arc shares of a path table, counted a file at a time."""
    if counted is None:
        return None
    totals = {"arcs": 0, "circles": 0, "both": 0}
    for flags in _file_columns(store, markers, table, ["is_arc", "is_circle"]):
        for key, count in arc_circle_counts(flags).items():
            totals[key] += count
    return _shares_of(counted["rows"], **totals)


def _shares_of(paths: int, arcs: int, circles: int, both: int) -> dict:
    """The shares of `paths` paths with these counts (`pathset.arc_circle_counts`)."""
    shares = path_shares(paths, arcs, circles, both)
    # The arc share of only the arcs that are not circles too: the paper's arc share (its
    # circle and arc shares add up to its arc-or-circle share).
    arc_not_circle = path_shares(paths, arcs - both, 0, 0)["arc"]
    return {"paths": paths, **shares, "arc_not_circle": arc_not_circle}


def _transmission(
    store: Store, markers: dict[str, dict[int, dict]], mechanisms: dict | None
) -> dict | None:
    """The distribution of the mechanisms' least transmission angles, in degrees, read a
    file at a time: the histogram and the shares below each threshold counted file by file,
    the angles gathered into one float32 array whose quantiles are taken in place (4 bytes a
    mechanism, up to twice that while the array grows). None for a dataset without them (made
    before the column existed)."""
    if mechanisms is None or mechanisms["rows"] == 0:
        return None
    # Grown from the rows read, never sized from the markers' word: a marker claiming a
    # trillion rows must not allocate them.
    degrees = np.empty(min(mechanisms["rows"], 1 << 20), dtype=np.float32)
    edges = np.arange(0, 90 + TRANSMISSION_BIN_DEG, TRANSMISSION_BIN_DEG)
    counts = np.zeros(len(edges) - 1, dtype=np.int64)
    below = dict.fromkeys(TRANSMISSION_THRESHOLDS, 0)
    filled = 0
    try:
        angles = _file_columns(store, markers, "mechanisms", ["min_transmission_deg"])
        for rows in angles:
            part = rows.column(0).to_numpy()
            if filled + len(part) > mechanisms["rows"]:
                filled += len(part)  # more rows than the markers say: refused below
                break
            if filled + len(part) > len(degrees):
                grown = np.empty(min(2 * (filled + len(part)), mechanisms["rows"]), np.float32)
                grown[:filled] = degrees[:filled]
                degrees = grown
            degrees[filled : filled + len(part)] = part
            filled += len(part)
            counts += np.histogram(part, bins=edges)[0]
            for threshold in below:
                below[threshold] += int(np.count_nonzero(part < threshold))
    except ValueError:  # no such column (pyarrow's ArrowInvalid is a ValueError)
        return None
    if filled != mechanisms["rows"]:
        raise ValueError(
            f"{store.uri}: the mechanisms table holds {filled:,} rows, its commit markers "
            f"say {mechanisms['rows']:,}"
        )
    quantiles = np.quantile(degrees, TRANSMISSION_QUANTILES, overwrite_input=True)
    return {
        "mechanisms": len(degrees),
        "quantiles": {
            str(q): float(v) for q, v in zip(TRANSMISSION_QUANTILES, quantiles, strict=True)
        },
        "share_below": {str(t): count / len(degrees) for t, count in below.items()},
        "histogram": {"bin_deg": TRANSMISSION_BIN_DEG, "counts": counts.tolist()},
    }


def _made_paths(markers: list[dict]) -> tuple[dict | None, dict | None]:
    """The counts and shares of every path curation made, from its markers alone: for a root
    that stores no `paths` table (a lean one), whose curators counted them as they made them."""
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


#: How `candidates_per_valid` measures the rejection sampler: position sets found per topology,
#: and the candidates after which a topology is abandoned (all of them counted).
MEASURE_VARIANTS = 5
MEASURE_MAX_CANDIDATES = 200_000
#: What a reader is told when candidates per valid were not measured, after the reason.
ASK_TO_MEASURE = (
    "--measure-candidates N measures the rejection sampler on N topologies per joint count"
)


def candidates_per_valid(
    run: dict | None, sample_topologies: int | None, seed: int
) -> tuple[dict[str, float] | None, str, dict | None]:
    """Candidates tried per valid mechanism by joint count, where they come from, and the
    sample measured here (None unless measured here).

    The figure depends on the topology generator, the rejection sampler, the seed and the
    sample size, never on the root's rows, and measuring it took most of `links stats`' time
    at every call. So it is measured only when asked (`sample_topologies` topologies per
    joint count, `MEASURE_VARIANTS` position sets each), else taken from the generation run
    when that used the rejection sampler (its own count of the candidates it tried), else
    None with the reason. It is not recorded in the root: stats opens roots read-only (they
    may be on S3, or another's), and a figure that does not depend on a root's rows does not
    belong with them.
    """
    if sample_topologies is not None:
        measured = measure_candidates_per_valid(
            range(MIN_DATASET_JOINTS, MAX_DATASET_JOINTS + 1),
            sample_topologies,
            MEASURE_VARIANTS,
            np.random.default_rng(seed),
            "rejection",
            max_candidates=MEASURE_MAX_CANDIDATES,
        )
        sample = {
            "sampler": "rejection",
            "topologies_per_joint_count": sample_topologies,
            "variants": MEASURE_VARIANTS,
            "max_candidates": MEASURE_MAX_CANDIDATES,
            "seed": seed,
        }
        source = (
            f"measured here: the rejection sampler on {sample_topologies} random topologies per "
            f"joint count, {MEASURE_VARIANTS} variants each"
        )
        return {str(n): e["candidates_per_valid"] for n, e in measured.items()}, source, sample
    if run and run["plan"]["sampler"] == "rejection":
        from_run = {
            size: entry["candidates_per_valid"] for size, entry in run["by_joint_count"].items()
        }
        return from_run, "the generation run (rejection sampler)", None
    why = "the root was made by the sequential sampler" if run else "no generation run recorded"
    return None, f"not measured ({why}); {ASK_TO_MEASURE}", None


def dataset_stats(root: str, sample_topologies: int | None = None, seed: int = 0) -> dict:
    """The statistics of the dataset at `root` as one JSON-ready dict; candidates per valid
    measured on `sample_topologies` topologies per joint count only when given
    (`candidates_per_valid`)."""
    if sample_topologies is not None and sample_topologies < 1:
        raise ValueError(f"sample_topologies must be a positive integer, got {sample_topologies}")
    store = Store.open(root, writable=False)
    run = store.read_json(f"{META}/summary.json")
    curation = store.read_json(f"{META}/curation_summary.json")
    markers = {stage: committed_shards(store, stage) for stage in set(TABLE_STAGE.values())}
    counts = {table: _counts(markers, table) for table in TABLE_NAMES}
    if not any(counts.values()):
        raise ValueError(f"{store.uri} holds no dataset tables")
    shares = {table: _shares(store, markers, table, counts[table]) for table in CURATION_TABLES}
    if counts["paths"] is None:
        counts["paths"], shares["paths"] = _made_paths(list(markers["curation"].values()))
    paths, mechanisms = counts["paths"], counts["mechanisms"]
    paths_per_mechanism = paths and mechanisms and paths["rows"] / mechanisms["rows"]
    candidates, source, sample = candidates_per_valid(run, sample_topologies, seed)
    return {
        "root": store.uri,
        "counts": counts,
        "paths_per_mechanism": paths_per_mechanism,
        "shares": shares,
        "min_transmission_deg": _transmission(store, markers, mechanisms),
        "candidates_per_valid": candidates,
        "candidates_per_valid_source": source,
        "candidates_per_valid_sample": sample,
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
