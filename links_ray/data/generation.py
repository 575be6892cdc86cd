"""The generation plan and its work units (shards), and the work of one shard.

Rows depend only on the seed and the mechanism count, never on workers, restarts or shard
boundaries: topology `i` draws everything (its topology, five valid position variants and its
negatives) from its own generator seeded by ``(seed, i)``. Its joint count is ``8 + i % 13``, so
the 8-20 joint mix is uniform and every shard holds topologies of one joint count, writing one
file per table into a single `n_joints` partition.

Ids: ``mechanism_id = 5 i + variant``; a negative's id is ``NEGATIVE_ID_BASE + 5 i + k``.

A root is extended in place: the plan of an extended root lists the sizes it held before
(`extended_from`), and each extension adds the shards of the mechanism ids it adds, numbered
after the earlier ones. Earlier shards are never rewritten, so their rows stay bit for bit; a
topology split by an extension writes its remaining variants in the new shards.

The engine and pyarrow: no Ray.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from itertools import pairwise

import numpy as np
import pyarrow as pa

from links_ray.data.commit import Failpoint, ShardWriter
from links_ray.data.schemas import (
    GENERATION_TABLES,
    SCHEMAS,
    TRAJECTORY_DTYPE,
    choose_tables,
    list_array,
)
from links_ray.data.store import Store
from links_ray.engine.inputs import DEFAULT_STEPS, as_transmission_deg
from links_ray.engine.kinematics.mechanism import MAX_DATASET_JOINTS, MIN_DATASET_JOINTS, Topology
from links_ray.engine.kinematics.sampling import (
    SAMPLERS,
    PositionSampler,
    PositionSearch,
    PositionSearchError,
)
from links_ray.engine.kinematics.solver import TopologySimulator
from links_ray.engine.kinematics.topology import TOPOLOGY_RULES, grow_topology
from links_ray.engine.kinematics.transmission import mechanism_transmission_deg

VARIANTS = 5
JOINT_COUNTS = MAX_DATASET_JOINTS - MIN_DATASET_JOINTS + 1
#: Topologies per shard: about five seconds of one core, so a lost shard costs little.
TOPOLOGIES_PER_SHARD = 1000
#: Topologies per written record batch: bounds a worker's memory whatever the shard size.
TOPOLOGIES_PER_BATCH = 100
#: Search budget per topology: candidates (rejection) or attempts (sequential). A topology that
#: exhausts it is replaced by the next one its generator draws, and counted as abandoned.
SEARCH_BUDGET = {"rejection": 1_000_000, "sequential": 10_000}
NEGATIVE_ID_BASE = 1 << 62
#: Extensions a root's plan may record: each adds a set of shards, so a run record listing
#: millions (written by hand, or by a hostile source) would make a plan of millions of shards.
MAX_EXTENSIONS = 1000
#: 2: the `min_transmission_deg` column, the turn checked between steps, `topology_rules`.
FORMAT_VERSION = 2


@dataclass(frozen=True)
class Shard:
    """A work unit: topologies `first`, `first + 13`, ... (`count` of them), all `n_joints`,
    writing those of their mechanisms whose ids are in `[low_id, high_id)` (their extension's)."""

    shard_id: int
    n_joints: int
    first: int
    count: int
    low_id: int
    high_id: int

    def topology_ids(self) -> range:
        """The shard's topology ids: `first`, `first + JOINT_COUNTS`, ... (`count` of them)."""
        return range(self.first, self.first + JOINT_COUNTS * self.count, JOINT_COUNTS)


@dataclass(frozen=True)
class GenerationPlan:
    """What a run produces; equal plans produce equal rows.

    `tables` are the tables written (`mechanisms` always): leaving a table out changes no row of the
    others, since every topology draws the same whatever is written. `topology_rules` picks the
    topology generator (engine.kinematics.topology). `min_transmission_deg` above 0 rejects valid
    mechanisms whose least transmission angle is below it, and searches on until the topology has
    its variants (or abandons it when its budget is spent). `extended_from` are the sizes
    the root held before it was extended to `mechanisms`, smallest first (empty for a root made
    at its size): each extension's shards follow the earlier ones'.
    """

    seed: int
    mechanisms: int
    sampler: str = "sequential"
    topologies_per_shard: int = TOPOLOGIES_PER_SHARD
    variants: int = VARIANTS
    steps: int = DEFAULT_STEPS
    format: int = FORMAT_VERSION
    tables: tuple[str, ...] = GENERATION_TABLES
    topology_rules: str = TOPOLOGY_RULES[0]
    min_transmission_deg: float = 0.0
    extended_from: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        for name in ("seed", "mechanisms", "topologies_per_shard"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise ValueError(f"{name} must be an integer, got {value!r}")
        if self.mechanisms < 1:
            raise ValueError(f"mechanisms must be at least 1, got {self.mechanisms}")
        if self.seed < 0:
            raise ValueError(f"seed must be non-negative, got {self.seed}")
        if self.topologies_per_shard < 1:
            raise ValueError("topologies_per_shard must be at least 1")
        if self.sampler not in SAMPLERS:
            raise ValueError(f"sampler must be one of {', '.join(SAMPLERS)}, got {self.sampler!r}")
        if self.topology_rules not in TOPOLOGY_RULES:
            raise ValueError(
                f"topology_rules must be one of {', '.join(TOPOLOGY_RULES)}, "
                f"got {self.topology_rules!r}"
            )
        # frozen: each set once, in canonical form
        degrees = as_transmission_deg(self.min_transmission_deg, "min_transmission_deg")
        object.__setattr__(self, "min_transmission_deg", degrees)
        tables = choose_tables(self.tables, GENERATION_TABLES, required="mechanisms")
        object.__setattr__(self, "tables", tables)
        object.__setattr__(
            self, "extended_from", _checked_sizes(self.extended_from, self.mechanisms)
        )

    @property
    def topologies(self) -> int:
        """Topologies the run draws: `mechanisms` over `variants`, rounded up."""
        return -(-self.mechanisms // self.variants)

    def config(self) -> dict:
        """The plan as `run.json` records it (JSON types: lists for tuples)."""
        return {
            **asdict(self),
            "tables": list(self.tables),
            "extended_from": list(self.extended_from),
        }

    def extended_to(self, mechanisms: int) -> GenerationPlan:
        """This plan's root extended to `mechanisms`: every row it holds kept, the rest added."""
        if mechanisms < self.mechanisms:
            raise ValueError(
                f"the root holds {self.mechanisms:,} mechanisms: a root is extended, it never "
                f"shrinks (asked for {mechanisms:,}); use a new root for fewer"
            )
        if mechanisms == self.mechanisms:
            return self
        extended_from = (*self.extended_from, self.mechanisms)
        return replace(self, mechanisms=mechanisms, extended_from=extended_from)

    def shards(self) -> list[Shard]:
        """Every shard of the run, in a fixed order: those of the first size, then each
        extension's."""
        shards: list[Shard] = []
        bounds = (0, *self.extended_from, self.mechanisms)
        for low_id, high_id in pairwise(bounds):
            shards += self._shards_of_ids(low_id, high_id, first_shard_id=len(shards))
        return shards

    def _shards_of_ids(self, low_id: int, high_id: int, first_shard_id: int) -> list[Shard]:
        """The shards writing mechanism ids `[low_id, high_id)`, numbered from
        `first_shard_id`: those of one joint count together, `topologies_per_shard` a shard."""
        shards = []
        topologies = range(low_id // self.variants, -(-high_id // self.variants))
        for residue in range(JOINT_COUNTS):
            first = topologies.start + (residue - topologies.start) % JOINT_COUNTS
            members = len(range(first, topologies.stop, JOINT_COUNTS))
            for start in range(0, members, self.topologies_per_shard):
                shards.append(
                    Shard(
                        shard_id=first_shard_id + len(shards),
                        n_joints=MIN_DATASET_JOINTS + residue,
                        first=first + JOINT_COUNTS * start,
                        count=min(self.topologies_per_shard, members - start),
                        low_id=low_id,
                        high_id=high_id,
                    )
                )
        return shards


def _checked_sizes(sizes: object, mechanisms: int) -> tuple[int, ...]:
    """`extended_from` as a tuple, checked: increasing positive sizes, each below `mechanisms`."""
    if isinstance(sizes, str) or not isinstance(sizes, tuple | list):
        raise ValueError(f"extended_from must be a list of sizes, got {sizes!r}")
    checked = tuple(sizes)
    if len(checked) > MAX_EXTENSIONS:
        raise ValueError(
            f"extended_from must hold at most {MAX_EXTENSIONS:,} sizes, got {len(checked):,}"
        )
    for size in checked:
        if isinstance(size, bool) or not isinstance(size, int | np.integer):
            raise ValueError(f"extended_from must hold integers, got {size!r}")
    if any(a >= b for a, b in pairwise((0, *checked, mechanisms))):
        raise ValueError(
            f"extended_from must be sizes from 1 up, each below the next and below mechanisms "
            f"({mechanisms}), got {list(checked)}"
        )
    return tuple(int(size) for size in checked)


@dataclass
class _Rows:
    """Column buffers of one table, turned into a record batch on flush."""

    columns: dict[str, list[np.ndarray]]

    @classmethod
    def empty(cls, table: str) -> _Rows:
        return cls({name: [] for name in SCHEMAS[table].names})

    def add(self, **values: np.ndarray) -> None:
        for name, value in values.items():
            self.columns[name].append(value)

    def __len__(self) -> int:
        first = next(iter(self.columns.values()))
        return sum(len(part) for part in first)

    def batch(self, table: str) -> pa.RecordBatch:
        schema = SCHEMAS[table]
        arrays = []
        for field in schema:
            parts = self.columns[field.name]
            if pa.types.is_list(field.type):
                rows = np.concatenate([p.reshape(len(p), -1) for p in parts])
                arrays.append(list_array(rows, field.type.value_type))
            else:
                arrays.append(pa.array(np.concatenate(parts), type=field.type))
        return pa.RecordBatch.from_arrays(arrays, schema=schema)


def mechanism_topology(mechanism_ids: np.ndarray) -> np.ndarray:
    """The topology id of each mechanism id, valid or negative (the inverse of the ids'
    arithmetic: ``5 i + variant``, ``NEGATIVE_ID_BASE + 5 i + k``)."""
    ids = np.asarray(mechanism_ids, dtype=np.int64)
    return np.where(ids >= NEGATIVE_ID_BASE, ids - NEGATIVE_ID_BASE, ids) // VARIANTS


def topology_rng(seed: int, topology_id: int) -> np.random.Generator:
    """The generator topology `topology_id` of a run draws everything from."""
    return np.random.default_rng([seed, topology_id])


def generate_shard(
    plan: GenerationPlan, shard: Shard, write: Callable[[str, pa.RecordBatch], None]
) -> dict:
    """Generate a shard's rows, handing record batches of the plan's tables to
    `write(table, batch)`.

    Returns the shard's statistics: topologies, mechanisms, candidates tried and valid sets
    found (abandoned topologies' included), valid sets below the plan's least transmission
    angle, negatives, topologies abandoned, and the seconds it took.
    """
    start = time.perf_counter()
    stats = {
        "topologies": 0,
        "mechanisms": 0,
        "candidates": 0,
        "valid": 0,
        "below_transmission": 0,
        "negatives": 0,
        "abandoned": 0,
    }
    for chunk in _chunks(shard.topology_ids(), TOPOLOGIES_PER_BATCH):
        rows = {table: _Rows.empty(table) for table in plan.tables}
        for topology_id in chunk:
            _generate_topology(plan, shard, topology_id, rows, stats)
        for table, buffer in rows.items():
            if len(buffer):
                write(table, buffer.batch(table))
    stats["seconds"] = time.perf_counter() - start
    return stats


def write_shard(
    store: Store,
    plan: GenerationPlan,
    shard: Shard,
    fence: Callable[[], None] | None = None,
    failpoint: Failpoint | None = None,
) -> dict:
    """Generate `shard` into `store` and commit it; returns its marker.

    `fence` runs just before the commit and raises if this writer may no longer commit. On any
    failure the attempt is aborted (nothing of it stays visible) and the error goes on up.
    """
    with ShardWriter(store, shard.shard_id, shard.n_joints, failpoint=failpoint) as writer:
        stats = generate_shard(plan, shard, writer.write)
        if fence is not None:
            fence()
        return writer.commit(stats)


def _search_topology(
    plan: GenerationPlan, n_joints: int, topology_id: int, stats: dict
) -> tuple[Topology, PositionSearch, np.ndarray, np.ndarray, np.ndarray]:
    """A topology with `plan.variants` valid position sets, each at least as far from a dead
    centre as the plan asks: (topology, its first search, the kept positions, their
    trajectories as stored, their least transmission angles). Topologies whose search spends
    its budget are replaced."""
    rng = topology_rng(plan.seed, topology_id)
    budget = SEARCH_BUDGET[plan.sampler]
    while True:
        topology = grow_topology(rng, n_joints, plan.topology_rules)
        sampler = PositionSampler(TopologySimulator.from_topology(topology), plan.steps)
        spent, positions, stored, least, first = 0, [], [], [], None
        try:
            while sum(map(len, positions)) < plan.variants:
                found = sampler.search(
                    plan.variants,
                    rng,
                    plan.sampler,
                    max_negatives=plan.variants if first is None else 0,
                    max_candidates=budget - spent,
                )
                if first is None:
                    first = found
                spent += found.candidates
                trajectories = found.trajectories.astype(TRAJECTORY_DTYPE)
                # From the trajectories as stored, so curation's per-path angles agree.
                angles = mechanism_transmission_deg(topology.order, trajectories)
                passing = angles >= plan.min_transmission_deg
                stats["below_transmission"] += int((~passing).sum())
                stats["valid"] += len(trajectories)
                positions.append(found.positions[passing])
                stored.append(trajectories[passing])
                least.append(angles[passing])
                if spent >= budget and sum(map(len, positions)) < plan.variants:
                    raise PositionSearchError(f"budget of {budget} spent")
        except PositionSearchError:
            stats["abandoned"] += 1
            stats["candidates"] += budget
            continue
        stats["candidates"] += spent
        kept = slice(plan.variants)
        return (
            topology,
            first,
            np.concatenate(positions)[kept],
            np.concatenate(stored)[kept],
            np.concatenate(least)[kept],
        )


def _generate_topology(
    plan: GenerationPlan, shard: Shard, topology_id: int, rows: dict[str, _Rows], stats: dict
) -> None:
    """Topology `topology_id`'s rows whose ids are the shard's. A topology split by an extension
    is searched again for its later variants, its search and negatives counted once: by the
    shard that writes its first variant."""
    first_id = plan.variants * topology_id
    variants = slice(max(shard.low_id - first_id, 0), min(shard.high_id - first_id, plan.variants))
    counted = stats if variants.start == 0 else dict.fromkeys(stats, 0)
    n_joints = shard.n_joints
    topology, found, positions, stored, least = _search_topology(
        plan, n_joints, topology_id, counted
    )
    adjacency, node_types = topology.adjacency, topology.node_types
    ids = first_id + np.arange(variants.start, variants.stop, dtype=np.int64)
    keep = len(ids)
    shared = {
        "topology_id": np.full(keep, topology_id, dtype=np.int64),
        "adjacency": adjacency.reshape(1, -1).repeat(keep, axis=0),
        "node_types": node_types.reshape(1, -1).repeat(keep, axis=0),
    }
    rows["mechanisms"].add(
        mechanism_id=ids,
        variant=np.arange(variants.start, variants.stop, dtype=np.int8),
        positions=positions[variants],
        min_transmission_deg=least[variants],
        **shared,
    )
    if "simulations" in rows:
        rows["simulations"].add(
            mechanism_id=ids,
            steps=np.full(keep, plan.steps, dtype=np.int16),
            trajectories=stored[variants],
        )
    stats["mechanisms"] += keep
    if variants.start > 0:
        return
    negatives = len(found.negatives)
    if negatives and "negatives" in rows:
        rows["negatives"].add(
            mechanism_id=NEGATIVE_ID_BASE + plan.variants * topology_id + np.arange(negatives),
            topology_id=np.full(negatives, topology_id, dtype=np.int64),
            variant=np.arange(negatives, dtype=np.int8),
            adjacency=adjacency.reshape(1, -1).repeat(negatives, axis=0),
            node_types=node_types.reshape(1, -1).repeat(negatives, axis=0),
            positions=found.negatives,
            locked_step=found.negative_step.astype(np.int16),
            locked_node=found.negative_node.astype(np.int16),
        )
    stats["topologies"] += 1
    stats["negatives"] += negatives


def _chunks(ids: range, size: int) -> Iterator[range]:
    for start in range(0, len(ids), size):
        yield ids[start : start + size]
