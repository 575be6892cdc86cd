"""Retrieval: find curated paths whose shape matches a drawn curve, and the mechanisms that
trace them where the curve was drawn (the paper's case study, as an index).

`RetrievalIndex` is the face of the search layer. Its rooms never import it: it passes them
its arrays (`search.arrays.IndexArrays`) and the scan's buffers (`search.query.ScanBuffers`),
as pynndescent's `NNDescent` passes plain arrays into its kernels. Each name is imported from
the room that defines it (this module re-exports none). The rooms are:

- `search.arrays`: `IndexArrays`, what a query reads;
- `search.query`: the query pipeline (scan, estimates, exact) and the stages' sizes;
- `search.build`: the build, streamed from the curated table;
- `search.cache`: the on-disk cache of built indexes and the lease that lets one process
  build each;
- `search.brute_force`: exact brute force over every path (the truth retrieval is measured by);
- `search.placement`: placing results in the query's frame;
- `search.kernels`, `search.mechanisms`: the compiled kernels, and the packed mechanisms that
  trace the paths again.

In memory an index holds, per path, its sketch and the row of its mechanism (about 270
bytes), and the packed mechanisms (about 90 bytes a path): no path's points.

An index may cover one part of the curated shards (those whose number is `part` modulo
`parts`), so that several Serve replicas split a dataset too large for one. The arrays of each
part are saved beside the data and reused while its curated shards are unchanged; a build
streams the curated table, so it needs memory only for what it keeps.

No Ray: the Serve app and the CLI wrap this module.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from links_ray.data.commit import committed_files, committed_shards
from links_ray.data.path_draw import DrawnPaths, PathDraw
from links_ray.data.store import Store
from links_ray.engine.inputs import (
    DEFAULT_K,
    MAX_DATASET_JOINTS,
    as_max_joints,
    as_transmission_deg,
    validate_query,
)
from links_ray.engine.kinematics.mechanism import reduce_mechanism
from links_ray.engine.kinematics.paths import normalization
from links_ray.engine.synthesis.plan import RetrievalResult
from links_ray.search import query as search_query
from links_ray.search.arrays import IndexArrays
from links_ray.search.brute_force import brute_force_many
from links_ray.search.build import BUILD_BLOCK, Basis, batch_points, build_arrays, curated_batches
from links_ray.search.cache import (
    BUILD_WAIT_S,
    ROW_ARRAYS,
    build_lease,
    cache_folder,
    check_part,
    load_index,
    save_index,
    shards_fingerprint,
)
from links_ray.search.mechanisms import MechanismBank
from links_ray.search.placement import degrees_or_none, into_query_frame
from links_ray.search.query import PROBED_ROWS, ScanBuffers, allowed_rows

__all__ = ["RetrievalIndex"]


@dataclass
class RetrievalIndex:
    """Curated paths, their codes and sketches, and the mechanisms that trace them.

    One query at a time: the scan writes into buffers the index keeps (callers that serve
    concurrent requests hold a lock, as the Serve app does). The query functions read the
    index's `arrays`, not the index.
    """

    store: Store
    files: list[str]  # the curated files indexed, in row order
    steps: int  # points per path
    mechanism_row: np.ndarray  # (N,) int32: each path's mechanism, a row of `bank`
    joint: np.ndarray  # (N,) int8
    sketches: np.ndarray  # (N, 2 * SKETCH_POINTS) uint8, see `search.kernels`
    transmission: np.ndarray  # (N,) float32: min_transmission_deg (NaN where not stored)
    # Rows are grouped by coarse list: list l is rows list_start[l]:list_start[l + 1], its
    # centroid centroids[l] (field codes). file_row[r] is row r's place in the curated files.
    list_start: np.ndarray  # (L + 1,) int64
    centroids: np.ndarray  # (L, DIMENSIONS) float32
    file_row: np.ndarray  # (N,) int32 or int64
    basis: Basis
    bank: MechanismBank
    part: int = 0
    parts: int = 1
    build_s: float = 0.0
    fingerprint: str = ""  # of the curated shards indexed (changes when any is redone)
    drawn: DrawnPaths | None = None  # the seeded draw of curated paths indexed, if not all
    _scan: ScanBuffers = field(init=False, repr=False)  # the scan's, kept between queries
    _n_joints: np.ndarray | None = field(default=None, init=False, repr=False)  # `n_joints`

    def __post_init__(self) -> None:
        self._scan = ScanBuffers(len(self))

    def __len__(self) -> int:
        return len(self.joint)

    @property
    def arrays(self) -> IndexArrays:
        """The index's arrays, as the query functions read them (the same arrays, no copy)."""
        return IndexArrays(
            steps=self.steps,
            mechanism_row=self.mechanism_row,
            joint=self.joint,
            sketches=self.sketches,
            transmission=self.transmission,
            list_start=self.list_start,
            centroids=self.centroids,
            file_row=self.file_row,
            basis=self.basis,
            bank=self.bank,
        )

    @property
    def nbytes(self) -> int:
        """Memory the index holds, the scan's output buffer included."""
        arrays = (
            *(getattr(self, name) for name in ROW_ARRAYS),
            self.list_start,
            self.centroids,
        )
        basis = self.basis.mean.nbytes + self.basis.components.nbytes
        # The scan's scores (float32) and likely variants (int8), kept between queries
        # (counted before the first scan allocates them).
        held = 5 * len(self) + (0 if self._n_joints is None else self._n_joints.nbytes)
        return sum(a.nbytes for a in arrays) + basis + self.bank.nbytes + held

    @property
    def n_joints(self) -> np.ndarray:
        """(N,) int16: the joints of each path's reduced mechanism (`reduce_mechanism`),
        counted from the packed mechanisms on first use (a fraction of a second a million
        paths) and kept."""
        if self._n_joints is None:
            self._n_joints = self.arrays.count_joints()
        return self._n_joints

    @property
    def mechanism_id(self) -> np.ndarray:
        """(N,) int64: each path's mechanism id (computed)."""
        return self.bank.ids[self.mechanism_row]

    @property
    def path_id(self) -> np.ndarray:
        """(N,) int64: each path's id, 32 * mechanism_id + joint (computed)."""
        return self.path_ids(np.arange(len(self)))

    def path_ids(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows),) int64: the path ids of these rows, 32 * mechanism_id + joint."""
        return self.arrays.path_ids(rows)

    def paths(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows), steps, 2) float32: the curated points of these rows, traced again."""
        return self.arrays.paths(rows)

    @classmethod
    def open(
        cls,
        root: str | Store,
        rebuild: bool = False,
        part: int = 0,
        parts: int = 1,
        wait_s: float = BUILD_WAIT_S,
        draw: PathDraw | DrawnPaths | None = None,
    ) -> RetrievalIndex:
        """Load the index of `root`'s curated shards numbered `part` modulo `parts` (all, by
        default) saved beside the data, or build (and save) it; `rebuild`: build it anyway.

        Of several processes opening one part at once (Serve replicas), the one holding the
        part's index lease builds and saves it; the others wait for it and load it, or, with
        `rebuild`, take the lease after it and build again. After `wait_s` seconds of waiting,
        `LeaseHeld` names the holder. A saved index that cannot be read, or was made from other
        curated shards, is rebuilt. Raises ValueError for a bad part or a root with no curated
        table in the part.

        With `draw`, the index holds only the paths of that seeded draw of the whole curated
        set (`data.path_draw`) that fall in the part, and is saved apart from the full index,
        under the draw's name. A `DrawnPaths` found on this root already (`DrawnPaths.of`)
        spares reading the curated ids again, part after part.
        """
        check_part(part, parts)
        if not wait_s >= 0:
            raise ValueError(f"wait_s must be zero or more, got {wait_s!r}")
        store = root if isinstance(root, Store) else Store.open(root, writable=False)
        curated = {
            shard: marker
            for shard, marker in committed_shards(store, "curation").items()
            if "curated" in marker["files"]
        }
        markers = {shard: marker for shard, marker in curated.items() if shard % parts == part}
        files = committed_files(store, "curated", markers)
        if not files:
            where = "" if parts == 1 else f" in part {part} of {parts}"
            raise ValueError(f"{store.uri} has no curated table{where} yet")
        if isinstance(draw, DrawnPaths):
            draw, drawn = draw.draw, draw
        elif draw is not None:  # a draw of the whole curated set: every shard decides
            drawn = DrawnPaths.of(store, committed_files(store, "curated", curated), draw)
        folder = cache_folder(part, parts, draw)
        if draw is None:
            drawn = None
            fingerprint = shards_fingerprint(markers)
            rows = sum(marker["rows"].get("curated", 0) for marker in markers.values())
        else:
            fingerprint = f"{draw.name} {shards_fingerprint(curated)}"
            rows = sum(drawn.rows_by_file[relative] for relative in files)
            if rows == 0:
                raise ValueError(
                    f"{store.uri}: the draw {draw.name} holds no path in part {part} of {parts}"
                )
        common = {
            "store": store,
            "files": files,
            "part": part,
            "parts": parts,
            "fingerprint": fingerprint,
            "drawn": drawn,
        }
        saved = None if rebuild else load_index(store, folder, fingerprint, rows)
        if saved is not None:
            return cls(**common, **saved)
        lease = build_lease(store, part, parts, folder, fingerprint, rows, rebuild, wait_s)
        if isinstance(lease, dict):  # another process built it meanwhile
            return cls(**common, **lease)
        try:
            start = time.perf_counter()
            arrays = build_arrays(store, files, rows, None if drawn is None else drawn.keeps)
            index = cls(**common, **arrays, build_s=time.perf_counter() - start)
            try:
                save_index(store, folder, fingerprint, arrays, index.build_s)
            except OSError:  # a read-only root: serve from memory, build again next time
                pass
        finally:
            if lease is not None:
                lease.release()
        return index

    def iter_points(self, block: int = BUILD_BLOCK) -> Iterator[tuple[int, np.ndarray]]:
        """(first file row, points (B, steps, 2) float32) of every path, in the curated
        files' order (row r of the index is file row `file_row[r]`), read from Parquet: the
        index holds no points."""
        start = 0
        keeps = None if self.drawn is None else self.drawn.keeps
        for batch in curated_batches(self.store, self.files, ["points"], block, keeps):
            points = batch_points(batch)
            yield start, points
            start += len(points)

    def probe(self, field_codes: np.ndarray, rows: int = PROBED_ROWS) -> tuple[np.ndarray, ...]:
        """The row ranges to scan for a query whose variants have these field codes: the
        lists nearest any variant, nearest first, until they hold `rows` rows, in row order
        (`scan_pieces`: starts, ends, at)."""
        return search_query.probe(self.arrays, field_codes, rows)

    def candidates(
        self,
        levels: np.ndarray,
        count: int,
        pieces: tuple[np.ndarray, ...],
        allowed: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """About `count` rows of the scanned `pieces` (`probe`) whose scan score is least, and
        their likely variants, among the rows `allowed` (`search.query.allowed_rows`; None:
        all): the scan (`search.query.candidates` says exactly)."""
        return search_query.candidates(self.arrays, levels, count, pieces, allowed, self._scan)

    def ranked(
        self,
        normalized: np.ndarray,
        k: int = DEFAULT_K,
        candidates: int | None = None,
        probed: int = PROBED_ROWS,
        min_transmission: float = 0.0,
        max_joints: int | None = None,
    ) -> list[tuple[int, float, int]]:
        """The k best (row, chamfer, variant), best first, for a normalized query, among the
        paths keeping `min_transmission` degrees (all, at 0) whose reduced mechanism has at
        most `max_joints` joints (any, at None); the scan of the lists nearest it, `probed`
        rows, passes on `candidates` paths (by default as `stage_sizes` says)."""
        # The joints are counted (once) only when a query limits them.
        counts = None if max_joints is None else self.n_joints
        allowed = allowed_rows(self.transmission, counts, min_transmission, max_joints)
        return search_query.ranked(
            self.arrays, normalized, k, candidates, probed, allowed, self._scan
        )

    def warm(self, seconds: float = 5.0, queries: int = 200) -> int:
        """Answer queries until `seconds` pass or `queries` are answered; return how many.
        Raises ValueError unless seconds >= 0 and queries >= 1.

        The first (an ellipse) loads the compiled kernels; asked with `max_joints`, it counts
        the paths' reduced joints (`n_joints`) too, before a user's query would. The rest are
        the index's own paths.
        On a small machine the first seconds of queries after a load run many times slower
        than later ones, and waiting instead of querying does not help; answering them before
        taking traffic keeps them from users.
        """
        if not (seconds >= 0 and queries >= 1):
            raise ValueError(f"warm needs seconds >= 0 and queries >= 1, got {seconds}, {queries}")
        if not len(self):
            return 0
        angle = np.linspace(0, 2 * np.pi, 100)
        ellipse = np.column_stack([np.cos(angle), 0.5 * np.sin(angle)])
        self.retrieve(ellipse, max_joints=MAX_DATASET_JOINTS)
        rows = np.random.default_rng(0).integers(len(self), size=queries - 1)
        start = time.perf_counter()
        answered = 1
        for path in self.paths(rows):
            if time.perf_counter() - start >= seconds:
                break
            self.retrieve(path)
            answered += 1
        return answered

    def retrieve(
        self,
        points: object,
        k: int = DEFAULT_K,
        min_transmission: object = 0.0,
        max_joints: object = None,
    ) -> list[RetrievalResult]:
        """The k best results for a query, best first, each with its mechanism in the query's
        frame (docs/reference/contract.md, HTTP API, describes a result), among the paths
        whose least transmission angle is at least `min_transmission` degrees and whose
        reduced mechanism has at most `max_joints` joints (None: any) (fewer than k if fewer
        do). A result's `points` and its mechanism's `adjacency`, `node_types` and `positions`
        are numpy arrays made for the answer, none of them the index's own
        (`engine.synthesis.plan.RetrievalResult`). Raises ValueError naming a bad query, k,
        min_transmission or max_joints."""
        query, k = validate_query(points, k)
        min_transmission_deg = as_transmission_deg(min_transmission, "min_transmission")
        most = as_max_joints(max_joints)
        normalized, query_matrix, query_offset = normalization(query)
        ranked = self.ranked(normalized, k, min_transmission=min_transmission_deg, max_joints=most)
        rows = np.array([row for row, _, _ in ranked], dtype=np.int64)
        # float64, the values the stored float32 points hold: what the answer has always held.
        paths = self.paths(rows).astype(np.float64)
        path_ids = self.path_ids(rows)
        results: list[RetrievalResult] = []
        for i, (row, distance, variant) in enumerate(ranked):
            joint = int(self.joint[row])
            mechanism_row = int(self.mechanism_row[row])
            adjacency, node_types, positions, index = reduce_mechanism(
                *self.bank.mechanism(mechanism_row), joint
            )
            placed = into_query_frame(
                adjacency, node_types, positions, index, variant, query_matrix, query_offset
            )
            results.append(
                {
                    "path_id": int(path_ids[i]),
                    "mechanism_id": int(self.bank.ids[mechanism_row]),
                    "joint": joint,
                    "chamfer": distance,
                    "min_transmission_deg": degrees_or_none(self.transmission[row]),
                    "n_joints": len(node_types),
                    "points": paths[i],
                    "mechanism": {
                        "adjacency": adjacency,
                        "node_types": node_types,
                        "positions": placed,
                    },
                    "mechanism_joint": index,
                }
            )
        return results

    def brute_force(self, points: ArrayLike, k: int = DEFAULT_K) -> list[tuple[int, float, int]]:
        """Exact k best (row, chamfer, variant) over every path and variant, best first."""
        return self.brute_force_many([points], k)[0]

    def brute_force_many(
        self, queries: list[ArrayLike], k: int = DEFAULT_K
    ) -> list[list[tuple[int, float, int]]]:
        """`brute_force` of each query, in one pass over the curated points
        (`search.brute_force` says how). Raises ValueError naming a bad query."""
        return brute_force_many(self.arrays, self.iter_points, queries, k, self._scan)
