"""A small end-to-end run of the engine on one core: topologies, valid positions, simulations.

`links demo` writes `mechanisms.jsonl` (one mechanism per line: the fields of
docs/reference/contract.md, Mechanisms, plus the traced path of its last joint) and
`summary.json` into a local folder.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from pathlib import Path

import numpy as np

from links_ray.engine.sampling import PositionSampler, Sampler
from links_ray.engine.solver import TopologySimulator
from links_ray.engine.topology import random_topology

VARIANTS = 5


def run_demo(
    out: str | Path, mechanisms: int = 100, seed: int = 0, sampler: Sampler = "sequential"
) -> dict:
    """Generate `mechanisms` valid mechanisms (five variants per topology) into `out`."""
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    start = time.perf_counter()
    written, candidates, sizes = 0, 0, Counter()
    with open(folder / "mechanisms.jsonl", "w") as lines:
        topology_id = 0
        while written < mechanisms:
            adjacency, node_types = random_topology(rng)
            simulator = TopologySimulator(adjacency, node_types)
            found = PositionSampler(simulator).search(VARIANTS, rng, sampler)
            candidates += found.candidates
            last = simulator.topology.last_joint
            for variant in range(min(VARIANTS, mechanisms - written)):
                record = {
                    "mechanism_id": written,
                    "topology_id": topology_id,
                    "variant": variant,
                    "adjacency": adjacency.tolist(),
                    "node_types": node_types.tolist(),
                    "positions": found.positions[variant].tolist(),
                    "last_joint": last,
                    "last_joint_path": found.trajectories[variant, last].round(6).tolist(),
                }
                lines.write(json.dumps(record) + "\n")
                written += 1
                sizes[len(node_types)] += 1
            topology_id += 1
    elapsed = time.perf_counter() - start
    summary = {
        "out": str(folder),
        "mechanisms": written,
        "topologies": topology_id,
        "sampler": sampler,
        "candidates_per_valid": candidates / (topology_id * VARIANTS),
        "joint_counts": dict(sorted(sizes.items())),
        "seconds": round(elapsed, 3),
    }
    (folder / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary
