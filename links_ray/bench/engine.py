"""Benchmarks behind `links bench`: the paper's Table 1, one mechanism per call, and the
position samplers.

Each function returns a plain dict (the `--json` output); `format_*` renders it as a table with
the paper's figures beside ours. Timings are wall-clock on this machine, after compilation.
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from links_ray.bench.machine import machine_info
from links_ray.cli import report
from links_ray.engine.inputs import DEFAULT_STEPS
from links_ray.engine.kinematics.mechanism import CRANK_CENTER, CRANK_TIP, MAX_DATASET_JOINTS
from links_ray.engine.kinematics.reference import simulate_reference
from links_ray.engine.kinematics.sampling import (
    SAMPLERS,
    PositionSampler,
    measure_candidates_per_valid,
)
from links_ray.engine.kinematics.solver import (
    TopologySimulator,
    simulate,
    simulate_batch,
    topology_cache,
)
from links_ray.engine.kinematics.topology import random_topology

#: Table 1 of the paper: seconds to simulate 10,000 random mechanisms (mean of 10 runs).
PAPER_TABLE1_S = {
    "non_vectorized_1_thread": 454.864,
    "vectorized_1_thread": 10.994,
    "parallel_80_threads": 0.5557,
    "v100_gpu": 0.1823,
}
#: The paper's figure: more than 500 random position sets per valid mechanism, on average.
PAPER_CANDIDATES_PER_VALID = 500

Workload = list[tuple[np.ndarray, np.ndarray, np.ndarray]]


def random_candidates(node_types: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` position sets drawn as the paper draws them: crank pose fixed, the rest uniform."""
    positions = rng.random((count, len(node_types), 2))
    positions[:, 0] = CRANK_CENTER
    positions[:, 1] = CRANK_TIP
    return positions


def table1_workload(topologies: int = 100, per_topology: int = 100, seed: int = 0) -> Workload:
    """Random topologies (8-20 joints) with random candidate positions each."""
    rng = np.random.default_rng(seed)
    workload = []
    for _ in range(topologies):
        adjacency, node_types = random_topology(rng)
        workload.append((adjacency, node_types, random_candidates(node_types, per_topology, rng)))
    return workload


def _timed(run: Callable[[], object], repeats: int) -> list[float]:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return times


def _simulate_workload(workload: Workload, steps: int, buffer: np.ndarray) -> int:
    """Simulate every candidate, the solution path found once per topology; returns valid count."""
    valid = 0
    for adjacency, node_types, positions in workload:
        simulator = TopologySimulator(adjacency, node_types)
        size = positions.shape[0] * simulator.n_joints * steps * 2
        out = buffer[:size].reshape(positions.shape[0], simulator.n_joints, steps, 2)
        _, lock_step, _ = simulator.run(positions, steps, out=out)
        valid += int(np.count_nonzero(lock_step < 0))
    return valid


def _simulate_threaded(workload: Workload, steps: int, buffers: list[np.ndarray]) -> int:
    """`_simulate_workload` split by topology over one thread per buffer (kernels drop the GIL)."""
    threads = len(buffers)
    with ThreadPoolExecutor(threads) as pool:
        parts = pool.map(
            _simulate_workload,
            [workload[i::threads] for i in range(threads)],
            [steps] * threads,
            buffers,
        )
        return sum(parts)


def _summary(times: list[float]) -> dict[str, float]:
    return {
        "mean_s": statistics.fmean(times),
        "std_s": statistics.stdev(times) if len(times) > 1 else 0.0,
        "best_s": min(times),
    }


def bench_simulate(
    repeats: int = 5,
    reference_subset: int = 200,
    topologies: int = 100,
    per_topology: int = 100,
    seed: int = 0,
) -> dict:
    """Table 1 on this machine, plus full-turn throughput on valid mechanisms."""
    steps = DEFAULT_STEPS
    workload = table1_workload(topologies, per_topology, seed)
    candidates = topologies * per_topology
    threads = os.cpu_count() or 1
    buffers = [np.empty(per_topology * MAX_DATASET_JOINTS * steps * 2) for _ in range(threads)]
    buffer = buffers[0]

    # Row 1: the plain-Python solver on a subset, spread over the topologies, scaled up.
    per = max(1, reference_subset // topologies)
    subset = [(a, t, p[:per]) for a, t, p in workload]
    subset_size = per * topologies

    def run_reference() -> None:
        for adjacency, node_types, positions in subset:
            for candidate in positions:
                try:
                    simulate_reference(adjacency, node_types, candidate, steps)
                except ValueError:  # LockingError: counted, as the paper counts it
                    pass

    reference_time = _timed(run_reference, 1)[0]

    valid = _simulate_workload(workload, steps, buffer)  # also compiles outside the timing
    serial = _timed(lambda: _simulate_workload(workload, steps, buffer), repeats)
    parallel = _timed(lambda: _simulate_threaded(workload, steps, buffers), repeats)

    # Full 200-step turns of valid mechanisms, the dataset's own workload.
    rng = np.random.default_rng(seed + 1)
    valid_sets = []
    for adjacency, node_types, _ in workload:
        simulator = TopologySimulator(adjacency, node_types)
        found = PositionSampler(simulator).search(per_topology, rng, "sequential")
        valid_sets.append((adjacency, node_types, found.positions))
    full = _timed(lambda: _simulate_workload(valid_sets, steps, buffer), repeats)

    return {
        "benchmark": "simulate",
        "machine": machine_info(),
        "candidates": candidates,
        "valid_candidates": valid,
        "steps": steps,
        "topologies": topologies,
        "non_vectorized_1_thread": {
            "subset": subset_size,
            "subset_s": reference_time,
            "scaled_s": reference_time * candidates / subset_size,
        },
        "compiled_1_thread": _summary(serial),
        "compiled_all_cores": {**_summary(parallel), "threads": threads},
        "valid_full_turn": {
            **_summary(full),
            "mechanisms": topologies * per_topology,
            "per_second_per_core": topologies * per_topology / min(full),
        },
        "paper_s": PAPER_TABLE1_S,
        "targets": {"compiled_1_thread_s": 0.15, "valid_per_second_per_core": 60_000},
    }


def valid_mechanisms(topologies: int, variants: int, seed: int) -> Workload:
    """`topologies` random topologies (8-20 joints) with `variants` valid position sets each,
    as the dataset holds them."""
    rng = np.random.default_rng(seed)
    found = []
    for _ in range(topologies):
        adjacency, node_types = random_topology(rng)
        sampler = PositionSampler(TopologySimulator(adjacency, node_types))
        found.append((adjacency, node_types, sampler.search(variants, rng, "sequential").positions))
    return found


def bench_simulate_one(
    mechanisms: int = 200, repeats: int = 7, variants: int = 5, seed: int = 0
) -> dict:
    """Full turns a second of valid mechanisms (8-20 joints, 200 steps) by entry point, one
    thread: `simulate` one mechanism a call (its topology seen before, and new), a prebuilt
    `TopologySimulator` one mechanism a call and one topology a call, and `simulate_batch`
    one topology a call."""
    steps = DEFAULT_STEPS
    topologies = -(-mechanisms // variants)
    workload = valid_mechanisms(topologies, variants, seed)
    singles = [
        (adjacency, node_types, pos)
        for adjacency, node_types, positions in workload
        for pos in positions
    ][:mechanisms]
    prebuilt = [(TopologySimulator(a, t), pos[None]) for a, t, pos in singles]
    by_topology = [(TopologySimulator(a, t), positions) for a, t, positions in workload]
    batch_count = sum(len(positions) for _, _, positions in workload)

    def one_new_topology() -> None:
        for adjacency, node_types, pos in singles:
            topology_cache.clear()  # as if every call brought a topology never seen
            simulate(adjacency, node_types, pos, steps)

    runs: dict[str, tuple[Callable[[], object], int, str]] = {
        "simulate": (
            lambda: [simulate(a, t, pos, steps) for a, t, pos in singles],
            len(singles),
            "links_ray.simulate, one mechanism a call, its topology seen before",
        ),
        "simulate_new_topology": (
            one_new_topology,
            len(singles),
            "links_ray.simulate, one mechanism a call, a topology never seen",
        ),
        "prebuilt_one": (
            lambda: [simulator.simulate(pos, steps) for simulator, pos in prebuilt],
            len(singles),
            "TopologySimulator(...).simulate, built beforehand, one mechanism a call",
        ),
        "prebuilt_topology": (
            lambda: [simulator.simulate(positions, steps) for simulator, positions in by_topology],
            batch_count,
            f"TopologySimulator(...).simulate, built beforehand, {variants} sets a call",
        ),
        "simulate_batch": (
            lambda: [simulate_batch(a, t, positions, steps) for a, t, positions in workload],
            batch_count,
            f"links_ray.simulate_batch, one topology ({variants} sets) a call",
        ),
    }
    times: dict[str, list[float]] = {name: [] for name in runs}
    cpu: dict[str, list[float]] = {name: [] for name in runs}
    # The row that empties the topology cache at every call is timed after the others.
    cold = "simulate_new_topology"
    runs[cold][0]()  # compiles outside the timing
    for names in ([name for name in runs if name != cold], [cold]):
        for name in names:
            runs[name][0]()  # fills the topology cache outside the timing
        # Round robin, so that the load of a shared machine, and its drift, fall on every row.
        for _ in range(repeats):
            for name in names:
                start, start_cpu = time.perf_counter(), time.thread_time()
                runs[name][0]()
                cpu[name].append(time.thread_time() - start_cpu)
                times[name].append(time.perf_counter() - start)
    rows = {}
    for name, (_, count, what) in runs.items():
        rates = sorted(count / t for t in times[name])
        rows[name] = {
            "what": what,
            "mechanisms": count,
            **_summary(times[name]),
            "turns_per_second": count / min(times[name]),
            "turns_per_second_median": statistics.median(rates),
            "turns_per_second_low": rates[0],
            # CPU time of this thread: on a shared machine, what the calls themselves cost.
            "turns_per_cpu_second": count / min(cpu[name]),
            "turns_per_cpu_second_median": count / statistics.median(cpu[name]),
        }
    topology_cache.clear()
    return {
        "benchmark": "simulate-one",
        "machine": machine_info(),
        "steps": steps,
        "topologies": topologies,
        "repeats": repeats,
        "entry_points": rows,
    }


def bench_sample(per_joint_count: int = 10, count: int = 5, seed: int = 0) -> dict:
    """Valid mechanisms per core-second for each sampler, and candidates per valid by size."""
    rng = np.random.default_rng(seed)
    warm = TopologySimulator(*random_topology(rng, 8))
    for kind in SAMPLERS:  # compile outside the timing
        PositionSampler(warm).search(1, rng, kind)
    result: dict = {
        "benchmark": "sample",
        "machine": machine_info(),
        "count": count,
        "samplers": {},
    }
    for kind in SAMPLERS:
        # Every sampler sees the same topologies.
        by_size = measure_candidates_per_valid(
            range(8, 21), per_joint_count, count, np.random.default_rng(seed), kind
        )
        seconds = sum(count * per_joint_count / s["valid_per_second"] for s in by_size.values())
        result["samplers"][kind] = {
            "valid_per_core_second": count * per_joint_count * len(by_size) / seconds,
            "by_joint_count": by_size,
        }
    result["paper_candidates_per_valid"] = PAPER_CANDIDATES_PER_VALID
    result["targets"] = {"sequential_valid_per_core_second": 2000}
    return result


def format_simulate(result: dict) -> str:
    """Table 1 as text, ours beside the paper's."""
    ref = result["non_vectorized_1_thread"]
    one, allc, full = (
        result["compiled_1_thread"],
        result["compiled_all_cores"],
        result["valid_full_turn"],
    )
    paper = result["paper_s"]
    lines = [
        f"Table 1: {result['candidates']:,} random candidates ({result['topologies']} topologies, "
        f"8-20 joints, {result['steps']} steps; {result['valid_candidates']} valid)",
        f"{'method':<42}{'this machine (s)':>20}{'paper (s)':>14}",
        f"{'non-vectorized, 1 thread':<42}{ref['scaled_s']:>20.3f}"
        f"{paper['non_vectorized_1_thread']:>14.3f}",
        f"  (timed on {ref['subset']} candidates, {ref['subset_s']:.2f} s, scaled to all)",
        f"{'compiled, 1 thread':<42}{_pm(one):>20}{paper['vectorized_1_thread']:>14.3f}",
        f"{'compiled, all cores (' + str(allc['threads']) + ' threads)':<42}{_pm(allc):>20}"
        f"{paper['parallel_80_threads']:>14.4f}  (80 threads)",
        f"{'':<42}{'':>20}{paper['v100_gpu']:>14.4f}  (V100 GPU)",
        "",
        f"Full turns of valid mechanisms, 1 thread: {full['per_second_per_core']:,.0f} per second "
        f"({full['mechanisms']:,} in {full['best_s']:.3f} s best); target 60,000",
        f"Target: compiled 1 thread <= 0.15 s; measured {one['best_s']:.3f} s best",
    ]
    return "\n".join(lines)


def format_simulate_one(result: dict) -> str:
    """Turns a second by entry point: wall clock (best and slowest run) and CPU time."""
    rows = result["entry_points"]
    lines = [
        f"Full turns of valid mechanisms ({result['steps']} steps, 8-20 joints, "
        f"{result['topologies']} topologies), 1 thread, {result['repeats']} runs",
        f"{'entry point':<76}{'wall best':>11}{'slowest':>9}{'CPU best':>10}{'median':>9}",
    ]
    for row in rows.values():
        lines.append(
            f"{row['what']:<76}{row['turns_per_second']:>11,.0f}"
            f"{row['turns_per_second_low']:>9,.0f}{row['turns_per_cpu_second']:>10,.0f}"
            f"{row['turns_per_cpu_second_median']:>9,.0f}"
        )
    return "\n".join(lines)


def format_sample(result: dict) -> str:
    """Sampler throughput and candidates per valid mechanism by joint count."""
    samplers = result["samplers"]
    lines = [
        f"{kind}: {data['valid_per_core_second']:,.0f} valid mechanisms per core-second "
        f"({result['count']} variants per topology)"
        for kind, data in samplers.items()
    ]
    per_size = {
        kind: dict(report.by_joints(data["by_joint_count"])) for kind, data in samplers.items()
    }
    rows = [
        [n, *(report.number(per_size[kind][n]["candidates_per_valid"]) for kind in samplers)]
        for n in sorted(per_size["rejection"])
    ]
    lines += [
        "",
        report.table(["joints", *(f"{kind} cand/valid" for kind in samplers)], rows, names=0),
        f"Paper: more than {result['paper_candidates_per_valid']} candidates per valid on average "
        "(rejection sampler); target: sequential >= 2,000 valid per core-second",
    ]
    return "\n".join(lines)


def _pm(summary: dict[str, float]) -> str:
    return f"{summary['mean_s']:.4f} ± {summary['std_s']:.4f}"
