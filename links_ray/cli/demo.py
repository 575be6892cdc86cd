"""A small end-to-end run of the engine on one core: topologies, valid positions, simulations.

`links demo` writes `mechanisms.jsonl` (one mechanism per line: the fields of
docs/reference/contract.md, Mechanisms, plus the traced path of its last joint) and
`summary.json` into a local folder.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path

import numpy as np

from links_ray.cli import report
from links_ray.cli.arguments import json_option, non_negative_int, positive_int, print_result
from links_ray.cli.kernels import note_compiling
from links_ray.engine.kinematics.sampling import PositionSampler, Sampler
from links_ray.engine.kinematics.solver import TopologySimulator
from links_ray.engine.kinematics.topology import random_topology

VARIANTS = 5


def add_command(commands: argparse._SubParsersAction) -> None:
    """Register `links demo` on the `links` command's subparsers."""
    command = commands.add_parser(
        "demo", help="generate a few valid mechanisms with the engine and save them as JSON lines"
    )
    command.add_argument("--out", default="links-demo", help="output folder (default links-demo)")
    command.add_argument("--mechanisms", type=positive_int, default=100)
    command.add_argument("--seed", type=non_negative_int, default=0)
    command.add_argument("--sampler", choices=["sequential", "rejection"], default="sequential")
    json_option(command, "the summary")
    command.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """`links demo`: write the mechanisms, then print the summary."""
    note_compiling("demo")
    summary = run_demo(args.out, mechanisms=args.mechanisms, seed=args.seed, sampler=args.sampler)
    print_result(args, summary, report.format_demo)


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
